"""The version reported by ``/api/health``."""

from functools import lru_cache
from importlib import metadata

import visnerf


@lru_cache
def server_version() -> str:
    """Read once (the package metadata is on disk; ``/api/health`` must not wait for it)."""
    try:
        return metadata.version("visnerf")
    except metadata.PackageNotFoundError:
        return visnerf.__version__
