"""Request and response models. Every number a client sends is finite and bounded here; parameter
the frame is then checked once against the scene (rigid camera, parameter ranges) by
``SceneRenderer.view``."""

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag, model_validator

from visnerf.inference import Quality
from visnerf.lens import Projection

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
ImageFormat = Literal["png", "jpeg", "webp"]

MIN_IMAGE_SIZE = 8
ABSOLUTE_MAX_IMAGE_SIZE = 8192
"""Schema bound; the server's own limit (``Settings.max_image_size``) is checked on top."""

MEDIA_TYPES: dict[str, str] = {"png": "image/png", "jpeg": "image/jpeg", "webp": "image/webp"}


class OrbitCamera(BaseModel):
    """A camera orbiting the scene centre, in degrees (azimuth -180..180, elevation -90..90)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    azimuth: float = Field(ge=-360.0, le=360.0)
    elevation: float = Field(ge=-90.0, le=90.0)
    distance: float = Field(gt=0.0, le=1e6)


Row4 = Annotated[list[FiniteFloat], Field(min_length=4, max_length=4)]


class MatrixCamera(BaseModel):
    """A camera given by its 4x4 camera-to-world matrix (OpenGL axes, as in the data format)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    c2w: Annotated[list[Row4], Field(min_length=4, max_length=4)]
    """Checked to be rigid with the rest of the frame (``SceneRenderer.view``)."""


def _camera_kind(value: Any) -> str:
    if isinstance(value, dict):
        return "c2w" if "c2w" in value else "orbit"
    return "c2w" if isinstance(value, MatrixCamera) else "orbit"


Camera = Annotated[
    Annotated[OrbitCamera, Tag("orbit")] | Annotated[MatrixCamera, Tag("c2w")],
    Discriminator(_camera_kind),
]


class RenderRequest(BaseModel):
    """One frame. Missing fields take the scene's defaults (camera, fov, trained image size,
    parameter defaults)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    camera: Camera | None = None
    projection: Projection | None = None
    """``perspective`` or ``orthographic``; default: the one ``fov_deg`` or ``view_height`` implies,
    else the scene's own (orthographic for a scene trained from orthographic images)."""
    fov_deg: float | None = Field(default=None, gt=0.0, lt=180.0)
    """Horizontal field of view in degrees (perspective)."""
    view_height: float | None = Field(default=None, gt=0.0, le=1e6)
    """World units the image spans vertically (orthographic)."""
    width: int | None = Field(default=None, ge=MIN_IMAGE_SIZE, le=ABSOLUTE_MAX_IMAGE_SIZE)
    height: int | None = Field(default=None, ge=MIN_IMAGE_SIZE, le=ABSOLUTE_MAX_IMAGE_SIZE)
    params: dict[str, FiniteFloat] = Field(default_factory=dict, max_length=64)
    """Parameter values by name; missing ones take their default."""
    quality: Quality = "full"
    format: ImageFormat = "png"


class StreamRequest(RenderRequest):
    """One message of the interactive stream; ``seq`` is echoed in the frame header."""

    seq: int = Field(ge=-(2**53), le=2**53)
    format: ImageFormat = "jpeg"


MovieFormat = Literal["mp4", "gif"]
MOVIE_MEDIA_TYPES: dict[str, str] = {"mp4": "video/mp4", "gif": "image/gif"}
MovieState = Literal["queued", "running", "done", "failed", "cancelled"]
ABSOLUTE_MAX_FRAMES = 100_000
"""Schema bound; the server's own limit (``Settings.movie_max_frames``) is checked on top."""


class MovieRequest(BaseModel):
    """A movie job: a camera and parameter path (the document ``visnerf animate`` reads), or
    ``orbit`` frames circling the scene at its default camera and parameters; exactly one of them."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    path: dict[str, Any] | None = None
    """Keyframes: camera (orbit or c2w) with a lens (``fov``, or ``view_height`` for an orthographic
    movie; default the scene's), parameter values and time of each."""
    orbit: int | None = Field(default=None, ge=1, le=ABSOLUTE_MAX_FRAMES)
    """Instead of ``path``: this many frames of one turn around the scene."""
    fps: int = Field(default=30, ge=1, le=120)
    width: int = Field(default=512, ge=MIN_IMAGE_SIZE, le=ABSOLUTE_MAX_IMAGE_SIZE)
    height: int = Field(default=512, ge=MIN_IMAGE_SIZE, le=ABSOLUTE_MAX_IMAGE_SIZE)
    format: MovieFormat = "mp4"
    quality: Quality = "full"

    @model_validator(mode="after")
    def _one_source(self) -> "MovieRequest":
        if (self.path is None) == (self.orbit is None):
            raise ValueError("give either path or orbit (a number of frames), not both or neither")
        return self


class MovieJobCreated(BaseModel):
    job_id: str
    frames: int
    """Frames the movie will have."""
    status_url: str
    file_url: str


class MovieJobStatus(BaseModel):
    job_id: str
    scene_id: str
    state: MovieState
    frames_done: int
    frames_total: int
    error: str | None
    """Why the job failed (state ``failed``)."""
    frames_per_second: float | None
    """Rendering speed so far (null before the first frame)."""
    seconds_left: float | None
    """Estimated from that speed while running; 0 when done; null otherwise."""

class ParamAxis(BaseModel):
    name: str
    min: float
    max: float
    values: list[float]
    """The training values of this parameter."""
    default: float


class CameraDefaults(BaseModel):
    azimuth: float
    elevation: float
    distance: float
    fov_deg: float
    """The scene's field of view; for an orthographic scene the one that frames it alike at ``distance``."""
    projection: Projection = "perspective"
    """The projection of the training images, which a client shows by default."""
    view_height: float
    """World units an orthographic view spans vertically; for a perspective scene the one that frames
    it alike at ``distance``."""


class SceneSummary(BaseModel):
    id: str
    title: str
    kind: str
    params: list[ParamAxis]


class SceneDetail(SceneSummary):
    camera: CameraDefaults
    bbox: list[list[float]]
    image_size: tuple[int, int]
    """(width, height) of the images the scene was trained on."""
    background: list[float]
    training: dict[str, Any]
    version: str
    """Content hash of the checkpoint; changes when the scene is replaced."""


class Health(BaseModel):
    status: Literal["ok"] = "ok"
    version: str
    scenes: int
    ready: bool


class FrameSizeLimits(BaseModel):
    """The largest frames this server renders (a client sizes its frames to the screen within them)."""

    max_side: int
    """Largest width or height, in pixels."""
    max_full_pixels: int
    """Most pixels of a full-quality frame."""
    max_preview_pixels: int
    """Most pixels of a preview frame."""


class Readiness(BaseModel):
    ready: bool
    scenes: int
    failed: dict[str, str] = Field(default_factory=dict)
    """Checkpoints in the folder that could not be loaded, with the reason."""


class ErrorDetail(BaseModel):
    detail: Any


def json_safe(value: Any) -> Any:
    """Replace non-finite floats (not representable in JSON) by None, recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, str | int | bool) or value is None:
        return value
    return str(value)
