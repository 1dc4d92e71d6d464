"""The animation path's data: keyframed cameras and parameter values, and its JSON document.

A path is a list of keyframes, each a time (seconds), an orbit camera (azimuth and elevation in
degrees as ``visnerf.data.cameras.orbit_c2w`` takes them, distance from the origin, and a lens:
the horizontal field of view ``fov`` of a perspective camera or the ``view_height`` of an
orthographic one, the same projection along the whole path) and parameter values. Document,
version 1::

    {"version": 1, "camera_interpolation": "smooth", "param_interpolation": "linear",
     "keyframes": [{"time": 0.0,
                    "camera": {"azimuth": 30, "elevation": 15, "distance": 2.2, "fov": 30},
                    "params": {"isovalue": 0.4}}, ...]}

``parse.parse_path`` reads and checks one; ``AnimationPath.to_dict`` writes one.
"""

import math
from dataclasses import dataclass, field
from typing import Literal, Protocol, runtime_checkable

PATH_VERSION = 1
"""The version of the JSON document this module reads and writes."""

MAX_KEYFRAMES = 1000
"""Most keyframes a path may hold."""

CameraInterpolation = Literal["smooth", "linear"]
ParamInterpolation = Literal["linear", "smooth"]
CAMERA_INTERPOLATIONS: tuple[str, ...] = ("smooth", "linear")
PARAM_INTERPOLATIONS: tuple[str, ...] = ("linear", "smooth")


class PathError(ValueError):
    """An animation path that cannot be used; the message names the field, e.g.
    ``keyframes[2].camera.elevation: must be in [-90, 90], got 120``."""


@runtime_checkable
class AxisLike(Protocol):
    """A parameter axis, as ``visnerf.checkpoint.ParamAxis`` is."""

    @property
    def name(self) -> str: ...

    @property
    def min(self) -> float: ...

    @property
    def max(self) -> float: ...

    @property
    def default(self) -> float: ...


@dataclass(frozen=True)
class CameraKey:
    """An orbit camera looking at the origin, perspective (``fov``) or orthographic (``view_height``)."""

    azimuth: float
    """Degrees; 0 puts the camera on +z, 90 on +x (``orbit_c2w``)."""
    elevation: float
    """Degrees in [-90, 90]; 90 looks straight down from +y."""
    distance: float
    """Distance from the origin, > 0."""
    fov: float | None = None
    """Horizontal field of view in degrees, in (0, 180), of a perspective camera."""
    view_height: float | None = None
    """World units the image spans vertically, > 0, of an orthographic camera (``fov`` None)."""

    def __post_init__(self) -> None:
        check_camera(self, "camera")

    @property
    def orthographic(self) -> bool:
        return self.view_height is not None

    @property
    def lens(self) -> float:
        """The view height of an orthographic camera, else the field of view."""
        return self.view_height if self.view_height is not None else self.fov  # type: ignore[return-value]


def check_camera(camera: CameraKey, where: str) -> None:
    """Raise PathError naming ``where`` for a camera outside the ranges ``CameraKey`` documents."""
    if (camera.fov is None) == (camera.view_height is None):
        raise PathError(f"{where}: give fov (perspective) or view_height (orthographic), exactly one")
    lens = "fov" if camera.fov is not None else "view_height"
    for name in ("azimuth", "elevation", "distance", lens):
        value = getattr(camera, name)
        if not math.isfinite(value):
            raise PathError(f"{where}.{name}: must be a finite number, got {value}")
    if not -90.0 <= camera.elevation <= 90.0:
        raise PathError(f"{where}.elevation: must be in [-90, 90], got {camera.elevation:g}")
    if not camera.distance > 0.0:
        raise PathError(f"{where}.distance: must be above 0, got {camera.distance:g}")
    if camera.fov is not None and not 0.0 < camera.fov < 180.0:
        raise PathError(f"{where}.fov: must be in (0, 180), got {camera.fov:g}")
    if camera.view_height is not None and not camera.view_height > 0.0:
        raise PathError(f"{where}.view_height: must be above 0, got {camera.view_height:g}")


@dataclass(frozen=True)
class Keyframe:
    """The camera and parameter values at one time."""

    time: float
    """Seconds, >= 0; strictly increasing along a path."""
    camera: CameraKey
    params: dict[str, float] = field(default_factory=dict)
    """Parameter values by axis name; a missing name takes the axis default."""


@dataclass(frozen=True)
class AnimationPath:
    """Keyframes and how to interpolate between them (``interpolation.sample_frames``)."""

    keyframes: tuple[Keyframe, ...]
    """At least one, times strictly increasing."""
    camera_interpolation: str = "smooth"
    """``smooth`` (spherical Catmull-Rom of the view direction) or ``linear`` (slerp)."""
    param_interpolation: str = "linear"
    """``linear`` or ``smooth`` (monotone cubic: never overshoots a keyframe value)."""

    def __post_init__(self) -> None:
        if not self.keyframes:
            raise PathError("keyframes: must hold at least one keyframe")
        if self.camera_interpolation not in CAMERA_INTERPOLATIONS:
            raise PathError(f"camera_interpolation: must be one of {list(CAMERA_INTERPOLATIONS)}, "
                            f"got {self.camera_interpolation!r}")
        if self.param_interpolation not in PARAM_INTERPOLATIONS:
            raise PathError(f"param_interpolation: must be one of {list(PARAM_INTERPOLATIONS)}, "
                            f"got {self.param_interpolation!r}")
        for i, key in enumerate(self.keyframes):
            if not (math.isfinite(key.time) and key.time >= 0.0):
                raise PathError(f"keyframes[{i}].time: must be a finite number >= 0, got {key.time}")
            if i and not key.time > self.keyframes[i - 1].time:
                raise PathError(f"keyframes[{i}].time: must be after keyframes[{i - 1}].time "
                                f"({self.keyframes[i - 1].time:g}), got {key.time:g}")
            if key.camera.orthographic != self.orthographic:
                first, this = ("view_height", "fov") if self.orthographic else ("fov", "view_height")
                raise PathError(f"keyframes[{i}].camera.{this}: keyframes[0] has a {first}; a path keeps "
                                "one projection")

    @property
    def orthographic(self) -> bool:
        """Whether the path's cameras are orthographic (all of them are, or none)."""
        return self.keyframes[0].camera.orthographic

    @property
    def duration(self) -> float:
        """Seconds from the first keyframe to the last."""
        return self.keyframes[-1].time - self.keyframes[0].time

    def to_dict(self) -> dict:
        """The version-1 JSON document (``parse.parse_path`` reads it back to an equal path)."""
        return {
            "version": PATH_VERSION,
            "camera_interpolation": self.camera_interpolation,
            "param_interpolation": self.param_interpolation,
            "keyframes": [
                {
                    "time": key.time,
                    "camera": {"azimuth": key.camera.azimuth, "elevation": key.camera.elevation,
                               "distance": key.camera.distance,
                               ("view_height" if key.camera.orthographic else "fov"): key.camera.lens},
                    "params": dict(key.params),
                }
                for key in self.keyframes
            ],
        }
