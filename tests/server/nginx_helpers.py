"""Real nginx on loopback for the replica tests: as ``bench/server_load.py --mode
replicas`` runs it."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

from server_load import nginx_binary, running_nginx  # noqa: E402

__all__ = ["nginx_binary", "running_nginx"]
