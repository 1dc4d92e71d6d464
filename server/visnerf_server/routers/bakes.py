"""``GET /api/scenes/{id}/bake?NAME=VALUE...``: one parameter setting baked for the browser's
renderer (docs/bake_format.md), built in the background lane and kept (``bakes``)."""

import gzip
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query, Request, Response

from visnerf_server.dependencies import BakesDep, ClientKeyDep, MetricsDep, RegistryDep, ServerDep, SettingsDep
from visnerf_server.rate_limit import RateLimited
from visnerf_server.render_queue import QueueFullError
from visnerf_server.routers.render import etag_matches, scene_params_from_query
from visnerf_server.routers.scenes import ERRORS, SceneIdPath, find_scene

router = APIRouter(prefix="/api/scenes/{scene_id}/bake", tags=["bakes"])

BAKE_MEDIA_TYPE = "application/octet-stream"
BUILD_RETRY_S = 1
"""Seconds a client is asked to wait for a bake being built (a bundled scene's takes 0.3 to 5 s)."""
IMMUTABLE = "public, max-age=31536000, immutable"
"""A request that names the checkpoint's version (``v``, as the scene's details give it) gets a
bake that can never change: the version is the checkpoint's content hash."""
RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"content": {BAKE_MEDIA_TYPE: {}}, "description": "The bake (docs/bake_format.md). Headers: ETag, X-Cache."},
    304: {"description": "The bake named by If-None-Match is still this setting's"},
    **ERRORS,
    429: {"description": "This client's rate limit is spent; Retry-After says when enough is back"},
}


@router.get("", response_class=Response, responses=RESPONSES)
async def get_bake(
    scene_id: SceneIdPath,
    request: Request,
    registry: RegistryDep,
    bakes: BakesDep,
    settings: SettingsDep,
    server: ServerDep,
    metrics: MetricsDep,
    client: ClientKeyDep,
    v: Annotated[str | None, Query(description="The scene's version (its details' `version`): the answer "
                                    "is cached for good")] = None,
) -> Response:
    """The bake of the scene at a parameter setting: every query parameter but ``v`` is a scene
    parameter by name, missing ones take their default. 503 with Retry-After while it is built."""
    scene = find_scene(registry, scene_id)
    params = scene_params_from_query(request, {"v"})
    try:
        values = scene.renderer.resolve_params(params)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    key = bakes.key(scene, values)
    etag = key.etag()
    cache_control = IMMUTABLE if v is not None and v == scene.version[:16] else "no-cache"
    if etag_matches(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers={"ETag": etag, "Cache-Control": cache_control})
    retry = {"Retry-After": str(BUILD_RETRY_S)}

    def charge() -> None:  # the request that starts a build pays for it
        if server.limiter is not None:
            server.limiter.take(client, settings.bake_cost_pixels)

    try:
        data = bakes.lookup(scene, key, charge)
    except RateLimited as exc:
        metrics.rate_limited.inc()
        raise HTTPException(429, str(exc), {"Retry-After": exc.retry_after_header}) from None
    except QueueFullError as exc:
        raise HTTPException(503, f"{exc}; retry shortly", retry) from None
    except RuntimeError as exc:
        raise HTTPException(422, str(exc)) from None
    if data is None:
        raise HTTPException(503, "the bake of this setting is being built; retry shortly", retry)
    headers = {"ETag": etag, "Cache-Control": cache_control, "Vary": "Accept-Encoding", "X-Cache": "hit"}
    if "gzip" in request.headers.get("accept-encoding", "").lower():
        return Response(data, media_type=BAKE_MEDIA_TYPE, headers={**headers, "Content-Encoding": "gzip"})
    return Response(gzip.decompress(data), media_type=BAKE_MEDIA_TYPE, headers=headers)
