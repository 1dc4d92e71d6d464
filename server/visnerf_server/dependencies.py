"""Injected dependencies (``XDep = Annotated[X, Depends(get_x)]``); tests swap them with
``app.dependency_overrides``."""

from dataclasses import dataclass, field
from typing import Annotated

from fastapi import Depends, Header, HTTPException, status
from starlette.requests import HTTPConnection

from visnerf_server.auth import check_bearer
from visnerf_server.frame_cache import FrameCache
from visnerf_server.frames import FrameRenderer
from visnerf_server.metrics import Metrics
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


def get_server(connection: HTTPConnection) -> ServerState:
    server = getattr(connection.app.state, "server", None)
    if server is None:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, "server is starting", {"Retry-After": "1"})
    return server


ServerDep = Annotated[ServerState, Depends(get_server)]
SettingsDep = Annotated[Settings, Depends(get_settings)]


def get_registry(server: ServerDep) -> SceneRegistry:
    return server.registry


def get_render_queue(server: ServerDep) -> RenderQueue:
    return server.queue


def get_frame_cache(server: ServerDep) -> FrameCache:
    return server.cache


def get_metrics(server: ServerDep) -> Metrics:
    return server.metrics


RegistryDep = Annotated[SceneRegistry, Depends(get_registry)]
RenderQueueDep = Annotated[RenderQueue, Depends(get_render_queue)]
FrameCacheDep = Annotated[FrameCache, Depends(get_frame_cache)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]


def get_frame_renderer(
    queue: RenderQueueDep, cache: FrameCacheDep, metrics: MetricsDep, settings: SettingsDep
) -> FrameRenderer:
    return FrameRenderer(queue, cache, metrics, settings.render_timeout_s, settings.jpeg_quality)


FrameRendererDep = Annotated[FrameRenderer, Depends(get_frame_renderer)]


def require_token(server: ServerDep, authorization: Annotated[str | None, Header()] = None) -> None:
    """Uploads and deletes need ``Authorization: Bearer <token>``."""
    check_bearer(authorization, server.token)


TokenDep = Depends(require_token)
