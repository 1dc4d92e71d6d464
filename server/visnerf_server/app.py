"""The application factory: ``create_app(settings)`` wires settings, lifespan, routers, error
handlers, middleware and the static web client. Run it with ``visnerf serve`` or
``uvicorn --factory visnerf_server.app:create_app``."""

import asyncio
import contextlib
import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import torch
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.concurrency import run_in_threadpool
from uvicorn.middleware.proxy_headers import ProxyHeadersMiddleware

from visnerf.runtime import default_threads
from visnerf_server.api_docs import add_offline_docs
from visnerf_server.auth import resolve_token
from visnerf_server.bakes import BakeStore
from visnerf_server.dependencies import ServerState
from visnerf_server.frame_cache import FrameCache
from visnerf_server.metrics import Metrics
from visnerf_server.middleware import AccessLogMiddleware
from visnerf_server.movie_plans import MovieLimits
from visnerf_server.movies import MovieJobs
from visnerf_server.rate_limit import limiter_from_settings
from visnerf_server.registry import SceneRegistry
from visnerf_server.render_queue import RenderQueue
from visnerf_server.routers import bakes, health, movies, render, scenes, stream
from visnerf_server.schemas import json_safe
from visnerf_server.settings import Settings, get_settings
from visnerf_server.store_watch import JOIN_TIMEOUT_S, start_store_watcher
from visnerf_server.uploads import remove_stale_uploads
from visnerf_server.version import server_version

logger = logging.getLogger(__name__)


async def _load_scenes(server: ServerState, stop: threading.Event) -> None:
    errors = await run_in_threadpool(server.registry.load_all, server.settings.warmup, stop)
    server.load_errors = errors
    server.metrics.scenes.set(len(server.registry))
    server.ready = not stop.is_set()
    logger.info(
        "%d scene(s) ready from %s%s",
        len(server.registry),
        server.registry.checkpoints_dir,
        f"; {len(errors)} failed: {sorted(errors)}" if errors else "",
    )


def _lifespan(settings: Settings, metrics: Metrics):
    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        token = resolve_token(settings)
        registry = SceneRegistry(settings.checkpoints_dir, torch.device(settings.device), settings.frames())
        if not settings.checkpoints_dir.is_dir():
            logger.warning(
                "checkpoints folder %s does not exist yet; serving no scenes", settings.checkpoints_dir
            )
        elif removed := remove_stale_uploads(settings.checkpoints_dir):
            logger.info("removed %d stale upload temporaries", removed)
        threads = settings.threads if settings.threads is not None else default_threads()  # the quota or cores
        torch.set_num_threads(threads)
        workers = settings.render_workers or threads
        logger.info("rendering with %d torch thread(s)%s, %d render(s) at once", threads,
                    "" if settings.threads else " (CPU quota or cores)", workers)
        queue = RenderQueue(workers, settings.render_queue_size, metrics, settings.preview_workers)
        cache = FrameCache(settings.frame_cache_bytes, settings.frame_cache_entries)
        metrics.watch_cache(cache)
        jobs = MovieJobs(MovieLimits.from_settings(settings), queue, registry, metrics, settings.movie_dir)
        server = ServerState(
            settings, metrics, registry, queue, cache, token, limiter=limiter_from_settings(settings), movies=jobs,
            bakes=BakeStore(queue, metrics, settings.bake_cache_bytes),
        )
        app.state.server = server
        stop = threading.Event()
        loader: asyncio.Task | None = None
        if settings.background_load:
            loader = asyncio.create_task(_load_scenes(server, stop))
        else:
            await _load_scenes(server, stop)
        watcher = start_store_watcher(server, stop)  # other servers' uploads to the same folder
        try:
            yield
        finally:
            stop.set()
            server.ready = False
            if loader is not None:
                loader.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await loader
            if watcher is not None:
                await run_in_threadpool(watcher.join, JOIN_TIMEOUT_S)
            jobs.close()  # before the queue: a job must not take a queued frame's slot back meanwhile
            await run_in_threadpool(queue.shutdown)
            logger.info("render queue shut down")
            await run_in_threadpool(jobs.shutdown)

    return lifespan


def _clean_errors(errors: Any) -> list[dict[str, Any]]:
    """Validation errors without the echoed input or exception objects (JSON-safe, no NaN)."""
    return [
        {
            "loc": json_safe(list(e.get("loc", ()))),
            "msg": str(e.get("msg", "")),
            "type": str(e.get("type", "")),
        }
        for e in errors
    ]


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    return JSONResponse({"detail": _clean_errors(exc.errors())}, status_code=422)


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the app. Scenes load in the lifespan; ``/api/ready`` says when they are warm."""
    settings = settings if settings is not None else get_settings()
    metrics = Metrics()
    app = FastAPI(
        title="ViSNeRF render server",
        version=server_version(),
        description="Renders trained ViSNeRF scenes from any viewpoint and parameter value.",
        lifespan=_lifespan(settings, metrics),
        docs_url=None,  # FastAPI's pages load from a CDN: api_docs serves them from local files
        redoc_url=None,
    )

    async def app_settings() -> Settings:  # async: no thread of the pool for a constant
        return settings

    app.dependency_overrides[get_settings] = app_settings
    # No handler turns ValueError into 422: a client input is refused by an explicit
    # HTTPException(422) where it is checked, so that a ValueError from a bug is a 500.
    app.add_exception_handler(RequestValidationError, _validation_error)  # type: ignore[arg-type]
    app.include_router(health.router)
    app.include_router(scenes.router)
    app.include_router(render.router)
    app.include_router(bakes.router)
    app.include_router(stream.router)
    app.include_router(movies.router)
    app.include_router(health.metrics_router)
    add_offline_docs(app, settings.docs_assets_dir)
    if settings.client_dir is not None and settings.client_dir.is_dir():
        app.mount("/", StaticFiles(directory=settings.client_dir, html=True), name="client")
    app.add_middleware(
        AccessLogMiddleware,
        metrics=metrics,
        max_request_bytes=settings.max_request_bytes,
        log_format=settings.log_format,
    )
    if settings.trusted_proxies:  # outermost: every layer sees the client, not the proxy
        app.add_middleware(ProxyHeadersMiddleware, trusted_hosts=list(settings.trusted_proxies))
    return app
