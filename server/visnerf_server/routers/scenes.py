"""Scene listing, details, uploads and deletion."""

from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Path, Request, Response
from fastapi.responses import JSONResponse

from visnerf.inference import choose_lens
from visnerf_server.dependencies import RegistryDep, ServerDep, TokenDep
from visnerf_server.registry import SCENE_ID_PATTERN, Scene, SceneRegistry
from visnerf_server.schemas import (
    CameraDefaults,
    ErrorDetail,
    ParamAxis,
    SceneDetail,
    SceneSummary,
    json_safe,
)
from visnerf_server.uploads import delete_scene_alone, receive_checkpoint

router = APIRouter(prefix="/api/scenes", tags=["scenes"])

SceneIdPath = Annotated[
    str,
    Path(pattern=SCENE_ID_PATTERN, description="File stem of `<id>.safetensors` in the checkpoints folder"),
]
LOADING_RETRY_S = 1
"""Seconds a client is asked to wait for a scene that is still loading at start-up."""
ERRORS: dict[int | str, dict[str, Any]] = {code: {"model": ErrorDetail} for code in (401, 403, 404, 413, 422, 503)}


def find_scene(registry: SceneRegistry, scene_id: str) -> Scene:
    scene = registry.get(scene_id)
    if scene is None:
        if registry.pending(scene_id):
            raise HTTPException(503, f"scene {scene_id!r} is still loading", {"Retry-After": str(LOADING_RETRY_S)})
        raise HTTPException(404, f"unknown scene {scene_id!r}")
    return scene


def scene_summary(scene: Scene) -> SceneSummary:
    info = scene.renderer.info
    params = [
        ParamAxis(name=a.name, min=a.min, max=a.max, values=list(a.values), default=a.default)
        for a in info.params
    ]
    return SceneSummary(id=scene.id, title=info.title, kind=info.kind, params=params)


def scene_detail(scene: Scene) -> SceneDetail:
    info = scene.renderer.info
    camera = info.camera
    fov_deg, _ = choose_lens(camera, projection="perspective")
    _, view_height = choose_lens(camera, projection="orthographic")
    return SceneDetail(
        **scene_summary(scene).model_dump(),
        camera=CameraDefaults(
            azimuth=float(camera.get("azimuth", 0.0)),
            elevation=float(camera.get("elevation", 0.0)),
            distance=float(camera.get("distance", 4.0)),
            fov_deg=float(fov_deg),  # type: ignore[arg-type]
            projection="orthographic" if "view_height" in camera else "perspective",
            view_height=float(view_height),  # type: ignore[arg-type]
        ),
        bbox=[list(map(float, corner)) for corner in info.bbox],
        image_size=(int(info.image_size[0]), int(info.image_size[1])),
        background=list(map(float, info.background)),
        training=json_safe(dict(info.training)),
        version=scene.version[:16],
    )


@router.get("", response_model=list[SceneSummary], responses={503: {"model": ErrorDetail}})
def list_scenes(registry: RegistryDep) -> list[SceneSummary]:
    """Every scene served; 503 with Retry-After while the folder's first load runs (a partial list
    would look final: a client would miss the scenes still on their way, and a proxy would not
    retry another replica)."""
    if registry.loading:
        raise HTTPException(503, "scenes are still loading", {"Retry-After": str(LOADING_RETRY_S)})
    return [scene_summary(scene) for scene in registry.list()]


@router.get("/{scene_id}", response_model=SceneDetail, responses=ERRORS)
def get_scene(scene_id: SceneIdPath, registry: RegistryDep) -> SceneDetail:
    return scene_detail(find_scene(registry, scene_id))


@router.put(
    "/{scene_id}",
    response_model=SceneDetail,
    responses={**ERRORS, 201: {"model": SceneDetail, "description": "Created"}},
    dependencies=[TokenDep],
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}},
        }
    },
)
async def upload_scene(scene_id: SceneIdPath, request: Request, server: ServerDep) -> Response:
    """Upload a ``.safetensors`` checkpoint as the raw body. 201 when new, 200 when it replaced one.

    The scene becomes visible only after every check passed; the swap is atomic. A second upload
    of the same id waits for the first to finish."""
    return await receive_checkpoint(request, server, scene_id, upload_answer)


def upload_answer(scene: Scene, created: bool) -> JSONResponse:
    """The PUT's response, rendered to bytes before the scene is committed."""
    body = scene_detail(scene).model_dump(mode="json")
    if created:
        return JSONResponse(body, status_code=201, headers={"Location": f"/api/scenes/{scene.id}"})
    return JSONResponse(body)


@router.delete("/{scene_id}", status_code=204, responses=ERRORS, dependencies=[TokenDep])
async def remove_scene(scene_id: SceneIdPath, server: ServerDep) -> Response:
    """Delete a scene (after any upload of the same id in progress)."""
    await delete_scene_alone(server, scene_id)
    return Response(status_code=204)
