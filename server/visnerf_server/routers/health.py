"""Liveness, readiness and metrics."""

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST

from visnerf_server.costs import FrameLimits
from visnerf_server.dependencies import MetricsDep, ServerDep, SettingsDep
from visnerf_server.schemas import FrameSizeLimits, Health, Readiness
from visnerf_server.version import server_version

router = APIRouter(prefix="/api", tags=["health"])


@router.get("/health", response_model=Health)
async def health(server: ServerDep) -> Health:
    """Liveness: answers as soon as the process serves HTTP. Async, dependencies too: it never
    waits for a thread of the pool that render requests fill."""
    return Health(version=server_version(), scenes=len(server.registry), ready=server.ready)


@router.get("/ready", response_model=Readiness, responses={503: {"model": Readiness}})
async def ready(server: ServerDep) -> JSONResponse:
    """Readiness: 503 until every scene is loaded and has rendered one tiny warm-up frame."""
    body = Readiness(ready=server.ready, scenes=len(server.registry), failed=server.load_errors)
    headers = None if server.ready else {"Retry-After": "1"}
    return JSONResponse(body.model_dump(), status_code=200 if server.ready else 503, headers=headers)


@router.get("/limits", response_model=FrameSizeLimits)
async def limits(settings: SettingsDep) -> FrameSizeLimits:
    """The largest frames this server renders: larger ones are refused (422), naming the limit."""
    frame = FrameLimits.from_settings(settings)
    return FrameSizeLimits(max_side=frame.max_side, max_full_pixels=frame.max_full_pixels,
                           max_preview_pixels=frame.max_preview_pixels)


metrics_router = APIRouter(tags=["metrics"])


@metrics_router.get("/metrics", include_in_schema=False)
async def metrics(metrics: MetricsDep) -> Response:
    """Prometheus exposition format."""
    return Response(metrics.render(), media_type=CONTENT_TYPE_LATEST)
