#!/usr/bin/env bash
# Set up .venv if needed and start the server with the bundled checkpoints on http://127.0.0.1:8000/
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then python3 -m venv .venv; fi
# With the train extra: the README's training and evaluation commands use this .venv too (the server
# alone needs ".[server]", as docker/Dockerfile.server installs it).
# (an install from before the server's commands were an entry point is installed again)
.venv/bin/python -c "import importlib.metadata as m, visnerf, visnerf_server
assert m.entry_points(group='visnerf.commands', name='server')" 2>/dev/null || {
  .venv/bin/python -m pip install -q torch==2.13.0 && .venv/bin/python -m pip install -q -e ".[train]"; }
exec .venv/bin/visnerf serve --host 127.0.0.1 --port "${PORT:-8000}" --checkpoints checkpoints "$@"
