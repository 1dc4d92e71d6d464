"""The version reported by ``/api/health``."""

from importlib import metadata

import visnerf


def server_version() -> str:
    try:
        return metadata.version("visnerf")
    except metadata.PackageNotFoundError:
        return visnerf.__version__
