"""Single frames: POST with a JSON body, or GET with query parameters (so ``<img src>`` and HTTP
caches work). Render handlers are ``async``: they wait on the bounded render queue without a
thread, and a client that disconnects meanwhile stops its render (``disconnect``)."""

import math
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from visnerf.inference import RenderCancelled
from visnerf_server.costs import FrameLimits
from visnerf_server.dependencies import ClientKeyDep, FrameRendererDep, RegistryDep, SettingsDep
from visnerf_server.disconnect import ClientDisconnected, until_disconnected
from visnerf_server.frames import FrameJob, FrameRenderer, prepare_frame
from visnerf_server.rate_limit import RateLimited
from visnerf_server.render_queue import QueueFullError, RenderTimeoutError, WouldOutwaitError
from visnerf_server.routers.scenes import ERRORS, SceneIdPath, find_scene
from visnerf_server.schemas import MEDIA_TYPES, ImageFormat, Projection, Quality, RenderRequest
from visnerf_server.settings import Settings

router = APIRouter(prefix="/api/scenes/{scene_id}/render", tags=["render"])

IMAGE_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "content": {media: {} for media in MEDIA_TYPES.values()},
        "description": "The frame. Headers: X-Render-Time-Ms, Server-Timing, X-Cache (hit or miss).",
    },
    **ERRORS,
    429: {"description": "This client's rate limit is spent; Retry-After says when enough is back"},
    504: {"description": "The render took longer than the per-request limit"},
}
CLIENT_CLOSED_REQUEST = 499
"""Status logged for a request whose client disconnected before its frame was ready (nginx's)."""
RESERVED_QUERY = {
    "azimuth",
    "elevation",
    "distance",
    "c2w",
    "fov_deg",
    "projection",
    "view_height",
    "width",
    "height",
    "quality",
    "format",
}


def etag_matches(if_none_match: str | None, etag: str) -> bool:
    """Whether an If-None-Match header names ``etag``."""
    return if_none_match is not None and etag in {t.strip() for t in if_none_match.split(",")}


def scene_params_from_query(request: Request, reserved: set[str]) -> dict[str, float]:
    """Every query parameter not in ``reserved`` as a scene parameter by its own name; a name
    given twice or a value that is not a number is a 422 naming it."""
    params: dict[str, float] = {}
    for name in {k for k, _ in request.query_params.multi_items()} - reserved:
        given = request.query_params.getlist(name)
        if len(given) != 1:
            raise _query_error(name, f"parameter {name!r} is given {len(given)} times")
        try:
            params[name] = float(given[0])
        except ValueError:
            raise _query_error(
                name, f"parameter {name!r} must be a number, got {given[0]!r}", "float_parsing"
            ) from None
    return params


async def render_response(
    request: Request,
    job: FrameJob,
    frames: FrameRenderer,
    settings: Settings,
    client: str,
    cache_control: str,
    if_none_match: str | None = None,
) -> Response:
    """Render (or reuse) one frame; map the rate limit to 429 and queue trouble to 503/504."""
    etag = job.etag()
    if etag_matches(if_none_match, etag):
        return Response(status_code=304, headers={"ETag": etag, "Cache-Control": cache_control})
    retry = {"Retry-After": str(settings.retry_after_s)}
    try:
        frame = await until_disconnected(request, frames.render_async(job, client))
    except ClientDisconnected:
        return Response(status_code=CLIENT_CLOSED_REQUEST)
    except RateLimited as exc:
        frames.metrics.rate_limited.inc()
        raise HTTPException(429, str(exc), {"Retry-After": exc.retry_after_header}) from None
    except RenderCancelled:
        raise HTTPException(503, "render cancelled; retry shortly", retry) from None
    except WouldOutwaitError as exc:
        wait = {"Retry-After": str(max(1, math.ceil(exc.retry_after_s)))}
        raise HTTPException(503, f"{exc}; retry later", wait) from None
    except QueueFullError as exc:
        raise HTTPException(503, f"{exc}; retry shortly", retry) from None
    except RenderTimeoutError as exc:
        if exc.started:
            raise HTTPException(
                504, f"render took longer than the limit of {settings.render_timeout_s} s"
            ) from None
        raise HTTPException(
            503, f"render waited in the queue longer than the limit of {settings.render_timeout_s} s", retry
        ) from None
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    headers = {**frame.timing_headers(), "ETag": etag, "Cache-Control": cache_control}
    return Response(frame.data, media_type=frame.media_type, headers=headers)


def _prepare(scene_id: str, body: RenderRequest, registry: RegistryDep, settings: Settings) -> FrameJob:
    scene = find_scene(registry, scene_id)
    try:
        return prepare_frame(scene, body, FrameLimits.from_settings(settings))
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None


@router.post("", response_class=Response, responses=IMAGE_RESPONSES)
async def render_post(
    scene_id: SceneIdPath,
    body: RenderRequest,
    request: Request,
    registry: RegistryDep,
    frames: FrameRendererDep,
    settings: SettingsDep,
    client: ClientKeyDep,
) -> Response:
    """Render one frame described by a JSON body."""
    job = _prepare(scene_id, body, registry, settings)
    return await render_response(request, job, frames, settings, client, "no-store")


def _query_error(name: str, message: str, kind: str = "value_error") -> RequestValidationError:
    return RequestValidationError([{"loc": ("query", name), "msg": message, "type": kind}])


def _parse_c2w(text: str) -> list[list[float]]:
    try:
        values = [float(v) for v in text.replace(";", ",").split(",")]
    except ValueError:
        raise _query_error("c2w", "c2w must be 16 comma-separated numbers (row-major 4x4)") from None
    if len(values) != 16:
        raise _query_error(
            "c2w", f"c2w must be 16 comma-separated numbers (row-major 4x4), got {len(values)}"
        )
    return [values[i : i + 4] for i in range(0, 16, 4)]


@router.get("", response_class=Response, responses=IMAGE_RESPONSES)
async def render_get(
    scene_id: SceneIdPath,
    request: Request,
    registry: RegistryDep,
    frames: FrameRendererDep,
    settings: SettingsDep,
    client: ClientKeyDep,
    azimuth: Annotated[float | None, Query(description="Orbit azimuth, degrees")] = None,
    elevation: Annotated[float | None, Query(description="Orbit elevation, degrees")] = None,
    distance: Annotated[float | None, Query(description="Orbit distance to the centre")] = None,
    c2w: Annotated[str | None, Query(description="Instead of the orbit: 16 numbers, row-major 4x4")] = None,
    fov_deg: Annotated[float | None, Query(description="Horizontal field of view, degrees (perspective)")] = None,
    projection: Annotated[Projection | None, Query(description="perspective or orthographic; default the "
                                                    "scene's, or the one fov_deg or view_height implies")] = None,
    view_height: Annotated[float | None, Query(description="World units the image spans vertically "
                                                "(orthographic)")] = None,
    width: Annotated[int | None, Query()] = None,
    height: Annotated[int | None, Query()] = None,
    quality: Annotated[Quality, Query()] = "full",
    format: Annotated[ImageFormat, Query()] = "png",
) -> Response:
    """The POST route through query parameters; every other query parameter is a scene parameter
    by its own name (``?azimuth=30&isovalue=0.4``). Orbit values left out take the scene's default."""
    scene = find_scene(registry, scene_id)
    params = scene_params_from_query(request, RESERVED_QUERY)
    body: dict[str, Any] = {"fov_deg": fov_deg, "width": width, "height": height, "params": params}
    body.update({k: v for k, v in (("projection", projection), ("view_height", view_height)) if v is not None})
    body.update(quality=quality, format=format)
    orbit = {"azimuth": azimuth, "elevation": elevation, "distance": distance}
    if c2w is not None:
        if any(v is not None for v in orbit.values()):
            raise _query_error("c2w", "give either c2w or azimuth/elevation/distance, not both")
        body["camera"] = {"c2w": _parse_c2w(c2w)}
    elif any(v is not None for v in orbit.values()):
        defaults = scene.renderer.info.camera
        body["camera"] = {k: (v if v is not None else defaults.get(k)) for k, v in orbit.items()}
    try:
        request_model = RenderRequest.model_validate(body)
    except ValidationError as exc:
        raise RequestValidationError(exc.errors()) from None
    job = _prepare(scene_id, request_model, registry, settings)
    return await render_response(
        request, job, frames, settings, client, "no-cache", request.headers.get("if-none-match")
    )
