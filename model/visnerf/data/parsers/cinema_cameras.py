"""Cameras of a Cinema database: the producers' angle conventions and the options they need.

Cinema's specification has no cameras. What a database holds decides where they come from:
- ``pycinema``: each ``.h5`` image's own metadata (``CameraPos``, ``CameraDir``, ``CameraUp``, and
  ``CameraHeight`` for an orthographic view or ``CameraAngle``, VTK's vertical view angle in
  degrees, for a perspective one).
- ``paraview`` (the phi/theta image extractor): the camera starts at the focal point + (0, 0, d)
  looking along -z with +y up, turns by ``phi`` about the view-up axis through the focal point
  (VTK's Azimuth) and by ``theta`` about its own right axis (VTK's Elevation, cumulative, so it
  runs over the poles): exactly ``orbit_c2w(phi, theta, d, focal)``.
- ``ascent``: position = centre + r Rz(phi) Rx(theta) (0, 0, 1), up = Rz(phi) Rx(theta) (0, 1, 0),
  looking at the centre of the data's bounding box, r = 1.25 x its diagonal.
The angle conventions write no lens, focal point or distance: those come from ``CinemaCamera``.
"""

import json
import math
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np

from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.data.errors import DatasetError

Convention = Literal["pycinema", "paraview", "ascent"]
CONVENTIONS: tuple[str, ...] = get_args(Convention)

CAMERA_FILE = "visnerf_camera.json"
"""The sidecar file in a database folder that gives what its angle columns lack."""

ASCENT_DISTANCE_PER_DIAGONAL = 1.25
"""Ascent's cinema cameras sit 1.25 bounding-box diagonals from the box centre."""

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class CinemaCamera:
    """What turns a Cinema database's rows into cameras, beside what the database itself says."""

    convention: Convention | None = None
    """``pycinema``, ``paraview`` or ``ascent``; None: detected from the database."""
    focal_point: Vec3 | None = None
    """The point the cameras orbit and look at (ParaView; Ascent without ``bounds``)."""
    distance: float | None = None
    """Camera distance from the focal point (ParaView; Ascent without ``bounds``)."""
    fov_deg: float | None = None
    """Horizontal field of view of a perspective camera, degrees."""
    view_height: float | None = None
    """World units an orthographic camera's image spans vertically (ParaView's parallel scale x 2)."""
    bounds: tuple[Vec3, Vec3] | None = None
    """The data's bounding box [[x0, y0, z0], [x1, y1, z1]]: Ascent's centre and distance, and the scene's box."""
    background: Vec3 = (1.0, 1.0, 1.0)
    """Colour that RGBA images are composited on, and the model's background."""
    kind: Literal["dvr", "ir"] = "dvr"
    """``dvr`` (volume rendering) or ``ir`` (isosurfaces): how the scene is described to clients."""

    def __post_init__(self) -> None:
        if self.convention is not None and self.convention not in CONVENTIONS:
            raise ValueError(f"camera convention must be one of {', '.join(CONVENTIONS)}, got {self.convention!r}")
        for name in ("distance", "fov_deg", "view_height"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        if self.fov_deg is not None and not self.fov_deg < 180:
            raise ValueError(f"fov_deg must be below 180 degrees, got {self.fov_deg}")
        if self.fov_deg is not None and self.view_height is not None:
            raise ValueError("give fov_deg (perspective) or view_height (orthographic), not both")
        if self.focal_point is not None and not all(math.isfinite(v) for v in self.focal_point):
            raise ValueError(f"focal_point must be finite, got {self.focal_point}")
        if self.bounds is not None and not all(hi > lo for lo, hi in zip(*self.bounds, strict=True)):
            raise ValueError(f"bounds must be [[x0, y0, z0], [x1, y1, z1]] with x1 > x0 etc., got {self.bounds}")
        if self.kind not in ("dvr", "ir"):
            raise ValueError(f"kind must be 'dvr' or 'ir', got {self.kind!r}")

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str) -> "CinemaCamera":
        """From a JSON object; unknown keys and bad values are refused, naming ``where``."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise DatasetError(f"{where}: unknown key(s) {unknown} (known: {', '.join(sorted(known))})")
        try:
            values: dict[str, Any] = dict(data)
            for key in ("focal_point", "background"):
                if key in values:
                    values[key] = _vec3(values[key], key)
            if "bounds" in values:
                box = values["bounds"]
                if not (isinstance(box, list) and len(box) == 2):
                    raise ValueError("bounds must be [[x0, y0, z0], [x1, y1, z1]]")
                values["bounds"] = (_vec3(box[0], "bounds[0]"), _vec3(box[1], "bounds[1]"))
            for key in ("distance", "fov_deg", "view_height"):
                if key in values and values[key] is not None:
                    values[key] = float(values[key])
            return cls(**values)
        except (TypeError, ValueError) as exc:
            raise DatasetError(f"{where}: {exc}") from None

    def over(self, base: "CinemaCamera") -> "CinemaCamera":
        """``base`` with every field this one sets (not None and not the default) taking precedence."""
        default = CinemaCamera()
        changes = {f.name: getattr(self, f.name) for f in fields(self)
                   if getattr(self, f.name) is not None and getattr(self, f.name) != getattr(default, f.name)}
        lens = {"fov_deg", "view_height"} & set(changes)
        if lens:  # a lens given here replaces the other kind of lens in the sidecar
            changes.setdefault("fov_deg", None)
            changes.setdefault("view_height", None)
        return replace(base, **changes)

    def intrinsics(self, width: int, height: int, what: str) -> Intrinsics:
        """The lens at the images' size; DatasetError naming ``what`` when neither lens is given."""
        if self.view_height is not None:
            return Intrinsics.from_view_height(width, height, self.view_height)
        if self.fov_deg is not None:
            return Intrinsics.from_fov(width, height, math.radians(self.fov_deg))
        raise DatasetError(f"{what}: the images' lens is not known: give fov_deg (perspective) or view_height "
                           f"(orthographic) in {CAMERA_FILE} or as an option")


def _vec3(value: Any, name: str) -> Vec3:
    if not (isinstance(value, (list, tuple)) and len(value) == 3):
        raise ValueError(f"{name} must be a list of 3 numbers, got {value!r}")
    return tuple(float(v) for v in value)  # type: ignore[return-value]


def read_camera_file(folder: Path) -> CinemaCamera:
    """The database's ``visnerf_camera.json``, or the defaults when it has none."""
    path = folder / CAMERA_FILE
    if not path.is_file():
        return CinemaCamera()
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path} is not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path} must hold a JSON object")
    return CinemaCamera.from_dict(data, str(path))


def paraview_c2w(phi_deg: float, theta_deg: float, focal_point: Vec3, distance: float) -> np.ndarray:
    """ParaView's phi/theta camera (module docstring): VTK's Azimuth(phi) then Elevation(theta)."""
    return orbit_c2w(phi_deg, theta_deg, distance, focal_point)


def _rz(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _rx(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)], [0.0, math.sin(a), math.cos(a)]])


def ascent_c2w(phi_deg: float, theta_deg: float, centre: Vec3, distance: float) -> np.ndarray:
    """Ascent's cinema camera: R = Rz(phi) Rx(theta) turns the camera at +z (up +y) about the centre;
    its look-at frame is R itself (right R x, up R y, back R z)."""
    rotation = _rz(phi_deg) @ _rx(theta_deg)
    c2w = np.eye(4)
    c2w[:3, :3] = rotation
    c2w[:3, 3] = np.asarray(centre, dtype=np.float64) + distance * rotation[:, 2]
    return c2w


def ascent_angles(back: np.ndarray) -> tuple[float, float]:
    """(phi, theta) in degrees of the Ascent camera whose position lies along unit ``back`` from the centre."""
    x, y, z = (float(v) for v in back)
    theta = math.degrees(math.acos(max(-1.0, min(1.0, z))))
    phi = math.degrees(math.atan2(x, -y)) if math.hypot(x, y) > 1e-12 else 0.0
    return phi, theta


def ascent_centre_distance(camera: CinemaCamera, what: str) -> tuple[Vec3, float]:
    """Ascent's look-at point and distance: from ``bounds``, else ``focal_point`` and ``distance``."""
    if camera.bounds is not None:
        lo, hi = (np.asarray(b, dtype=np.float64) for b in camera.bounds)
        centre = tuple(float(v) for v in 0.5 * (lo + hi))
        return centre, ASCENT_DISTANCE_PER_DIAGONAL * float(np.linalg.norm(hi - lo))  # type: ignore[return-value]
    if camera.focal_point is not None and camera.distance is not None:
        return camera.focal_point, camera.distance
    raise DatasetError(f"{what}: Ascent's cameras need the data's bounds (or focal_point and distance) in "
                       f"{CAMERA_FILE} or as options")


def paraview_focal_distance(camera: CinemaCamera, what: str) -> tuple[Vec3, float]:
    """ParaView's focal point and distance; DatasetError naming what is missing."""
    missing = [n for n in ("focal_point", "distance") if getattr(camera, n) is None]
    if missing:
        raise DatasetError(f"{what}: ParaView's phi/theta cameras need {' and '.join(missing)} in {CAMERA_FILE} "
                           "or as options (the database does not record them)")
    return camera.focal_point, camera.distance  # type: ignore[return-value]
