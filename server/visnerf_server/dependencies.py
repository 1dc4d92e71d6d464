"""Injected dependencies (``XDep = Annotated[X, Depends(get_x)]``); tests swap them with
``app.dependency_overrides``."""

from dataclasses import dataclass, field
from typing import Annotated

from fastapi import Depends, Header, HTTPException, status
from starlette.requests import HTTPConnection

from visnerf_server.auth import check_bearer
from visnerf_server.bakes import BakeStore
from visnerf_server.frame_cache import FrameCache
from visnerf_server.frames import FrameRenderer
from visnerf_server.keyed_locks import KeyedLocks
from visnerf_server.metrics import Metrics
from visnerf_server.movies import MovieJobs
from visnerf_server.rate_limit import ClientRateLimiter, client_key
from visnerf_server.registry import SceneRegistry
from visnerf_server.render_queue import RenderQueue
from visnerf_server.settings import Settings, get_settings


@dataclass
class ServerState:
    """What the lifespan builds: one per running app."""

    settings: Settings
    metrics: Metrics
    registry: SceneRegistry
    queue: RenderQueue
    cache: FrameCache
    token: str
    ready: bool = False
    load_errors: dict[str, str] = field(default_factory=dict)
    uploads_in_progress: int = 0
    limiter: ClientRateLimiter | None = None
    """Per-client token buckets for renders (None: ``rate_limit_pixels_per_s`` is 0)."""
    stream_sessions: int = 0
    """Stream sessions open now (``Settings.ws_max_sessions`` bounds them)."""
    scene_locks: KeyedLocks = field(default_factory=KeyedLocks)
    """Serialise the uploads and deletions of one scene id."""
    movies: MovieJobs | None = None
    """Movie jobs (None only in a state built without them)."""
    bakes: BakeStore | None = None
    """Bakes built (None only in a state built without them)."""


async def get_server(connection: HTTPConnection) -> ServerState:
    """Async, like the accessors below: a sync dependency waits for a thread of AnyIO's pool,
    which slow renders can fill, and ``/api/health`` and ``/api/ready`` must answer meanwhile."""
    server = getattr(connection.app.state, "server", None)
    if server is None:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, "server is starting", {"Retry-After": "1"})
    return server


ServerDep = Annotated[ServerState, Depends(get_server)]
SettingsDep = Annotated[Settings, Depends(get_settings)]


async def get_registry(server: ServerDep) -> SceneRegistry:
    return server.registry


async def get_render_queue(server: ServerDep) -> RenderQueue:
    return server.queue


async def get_frame_cache(server: ServerDep) -> FrameCache:
    return server.cache


async def get_metrics(server: ServerDep) -> Metrics:
    return server.metrics


async def get_movie_jobs(server: ServerDep) -> MovieJobs:
    if server.movies is None:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, "movie jobs are not available", {"Retry-After": "1"})
    return server.movies


async def get_bakes(server: ServerDep) -> BakeStore:
    if server.bakes is None:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, "bakes are not available", {"Retry-After": "1"})
    return server.bakes


BakesDep = Annotated[BakeStore, Depends(get_bakes)]
RegistryDep = Annotated[SceneRegistry, Depends(get_registry)]
RenderQueueDep = Annotated[RenderQueue, Depends(get_render_queue)]
FrameCacheDep = Annotated[FrameCache, Depends(get_frame_cache)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
MovieJobsDep = Annotated[MovieJobs, Depends(get_movie_jobs)]


async def get_frame_renderer(
    queue: RenderQueueDep, cache: FrameCacheDep, metrics: MetricsDep, settings: SettingsDep, server: ServerDep
) -> FrameRenderer:
    return FrameRenderer(queue, cache, metrics, settings.render_timeout_s, settings.jpeg_quality, server.limiter)


FrameRendererDep = Annotated[FrameRenderer, Depends(get_frame_renderer)]


async def get_client_key(connection: HTTPConnection, server: ServerDep) -> str:
    """Whose rate-limit bucket pays for this request's renders (``rate_limit.client_key``)."""
    host = connection.client.host if connection.client is not None else None
    return client_key(host, connection.headers.get("authorization"), server.token)


ClientKeyDep = Annotated[str, Depends(get_client_key)]


def require_token(server: ServerDep, authorization: Annotated[str | None, Header()] = None) -> None:
    """Uploads and deletes need ``Authorization: Bearer <token>``."""
    check_bearer(authorization, server.token)


TokenDep = Depends(require_token)
