"""``/docs`` (Swagger UI) and ``/redoc`` from files on this machine, never from a CDN.

FastAPI's own pages load their scripts and styles from a CDN (and ReDoc its fonts from Google), so
the app is built without them. They come back only when ``Settings.docs_assets_dir`` names a
folder holding the files (``swagger-ui-dist`` from npm has the Swagger UI ones, ``redoc`` the
ReDoc one); those are served at ``/docs-assets``. ``/openapi.json`` needs no assets and is always
served.
"""

import logging
from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

logger = logging.getLogger(__name__)

ASSETS_URL = "/docs-assets"
SWAGGER_FILES = ("swagger-ui-bundle.js", "swagger-ui.css")
REDOC_FILE = "redoc.standalone.js"
FAVICON_FILE = "favicon-32x32.png"
"""Shipped with swagger-ui-dist; where it is missing the browser gets a 404 from this server."""


def add_offline_docs(app: FastAPI, assets_dir: Path | None) -> list[str]:
    """Serve ``/docs`` and ``/redoc`` for which ``assets_dir`` has the files; returns their paths."""
    if assets_dir is None:
        return []
    if not assets_dir.is_dir():
        logger.warning("docs assets folder %s does not exist: /docs and /redoc are off", assets_dir)
        return []
    app.mount(ASSETS_URL, StaticFiles(directory=assets_dir), name="docs-assets")
    pages = []
    if all((assets_dir / name).is_file() for name in SWAGGER_FILES):
        _add_swagger(app)
        pages.append("/docs")
    if (assets_dir / REDOC_FILE).is_file():
        _add_redoc(app)
        pages.append("/redoc")
    missing = [name for name in (*SWAGGER_FILES, REDOC_FILE) if not (assets_dir / name).is_file()]
    if missing:
        logger.warning("docs assets folder %s lacks %s", assets_dir, ", ".join(missing))
    return pages


def _add_swagger(app: FastAPI) -> None:
    @app.get("/docs", include_in_schema=False)
    async def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title=f"{app.title} - Swagger UI",
            swagger_js_url=f"{ASSETS_URL}/{SWAGGER_FILES[0]}",
            swagger_css_url=f"{ASSETS_URL}/{SWAGGER_FILES[1]}",
            swagger_favicon_url=f"{ASSETS_URL}/{FAVICON_FILE}",
            swagger_ui_parameters={"validatorUrl": None},  # no badge fetched from an online validator
        )


def _add_redoc(app: FastAPI) -> None:
    @app.get("/redoc", include_in_schema=False)
    async def redoc() -> HTMLResponse:
        return get_redoc_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title=f"{app.title} - ReDoc",
            redoc_js_url=f"{ASSETS_URL}/{REDOC_FILE}",
            redoc_favicon_url=f"{ASSETS_URL}/{FAVICON_FILE}",
            with_google_fonts=False,
        )
