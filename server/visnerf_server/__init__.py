"""The ViSNeRF render server: a FastAPI app over a folder of trained checkpoints.

``visnerf_server.app.create_app(settings)`` builds it; ``visnerf serve`` runs it; ``visnerf submit``
uploads to it. Importing this package is cheap; the app's modules load on first use.
"""

from typing import Any

__all__ = ["Settings", "create_app", "get_settings"]


def __getattr__(name: str) -> Any:
    if name == "create_app":
        from visnerf_server.app import create_app

        return create_app
    if name in ("Settings", "get_settings"):
        from visnerf_server import settings

        return getattr(settings, name)
    raise AttributeError(f"module 'visnerf_server' has no attribute {name!r}")
