"""Read and check an animation path document (``keys`` describes it); every refusal is a
``PathError`` that names the field, e.g. ``keyframes[2].params.isovalue: must be in [0, 1], got 3``."""

import math
from collections.abc import Mapping, Sequence

import numpy as np

from visnerf.animation.keys import (
    CAMERA_INTERPOLATIONS,
    MAX_KEYFRAMES,
    PARAM_INTERPOLATIONS,
    PATH_VERSION,
    AnimationPath,
    AxisLike,
    CameraKey,
    Keyframe,
    PathError,
)
from visnerf.data.cameras import check_rigid_c2w
from visnerf.lens import Projection, choose_lens

TOP_LEVEL_KEYS = ("version", "camera_interpolation", "param_interpolation", "keyframes")
KEYFRAME_KEYS = ("time", "camera", "params")
ORBIT_CAMERA_KEYS = ("azimuth", "elevation", "distance", "fov", "view_height")
MATRIX_CAMERA_KEYS = ("c2w", "fov", "view_height")
LENS_KEYS = ("fov", "view_height")
LOOK_AT_TOLERANCE_DEG = 1.0
"""How far from the origin a ``c2w`` camera may look (the renderer's orbit cameras look at it)."""


def parse_path(doc: object, axes: Sequence[AxisLike], camera_defaults: Mapping[str, float]) -> AnimationPath:
    """The path a JSON document (already decoded, e.g. by ``json.loads``) describes.

    ``axes`` are the scene's parameter axes; ``camera_defaults`` its default camera (keys
    ``azimuth``, ``elevation``, ``distance``, ``fov`` or ``fov_deg``, and ``view_height`` for an
    orthographic scene, as ``SceneInfo.camera`` has them), used for camera fields a keyframe leaves
    out. The path's projection is that of the first keyframe naming a lens (``fov`` or
    ``view_height``), else the scene's; a keyframe naming none takes the scene's lens in it
    (``visnerf.lens.choose_lens``). Parameter values a keyframe leaves out take the axis default,
    so every keyframe of the result names every axis.
    """
    if not isinstance(doc, dict):
        raise PathError(f"path: must be a JSON object, got {_json_type(doc)}")
    _refuse_unknown_keys(doc, TOP_LEVEL_KEYS, "path")
    if "version" not in doc:
        raise PathError(f"version: missing (this reader takes version {PATH_VERSION})")
    version = doc["version"]
    if isinstance(version, bool) or version != PATH_VERSION:
        raise PathError(f"version: must be {PATH_VERSION}, got {version!r}")
    camera_interpolation = _choice(doc.get("camera_interpolation", "smooth"), CAMERA_INTERPOLATIONS,
                                   "camera_interpolation")
    param_interpolation = _choice(doc.get("param_interpolation", "linear"), PARAM_INTERPOLATIONS,
                                  "param_interpolation")
    raw_keys = doc.get("keyframes")
    if not isinstance(raw_keys, list):
        raise PathError(f"keyframes: must be a list of keyframes, got {_json_type(raw_keys)}")
    if not raw_keys:
        raise PathError("keyframes: must hold at least one keyframe")
    if len(raw_keys) > MAX_KEYFRAMES:
        raise PathError(f"keyframes: at most {MAX_KEYFRAMES} keyframes, got {len(raw_keys)}")
    defaults = _with_lens(camera_defaults, _projection(raw_keys, camera_defaults))
    keyframes = tuple(_keyframe(raw, f"keyframes[{i}]", axes, defaults) for i, raw in enumerate(raw_keys))
    return AnimationPath(keyframes, camera_interpolation, param_interpolation)


def _projection(raw_keys: list, camera_defaults: Mapping[str, float]) -> Projection:
    """The projection of the first keyframe that names a lens, else the scene's."""
    for raw in raw_keys:
        camera = raw.get("camera") if isinstance(raw, dict) else None
        if isinstance(camera, dict):
            if "view_height" in camera:
                return "orthographic"
            if "fov" in camera:
                return "perspective"
    return "orthographic" if "view_height" in camera_defaults else "perspective"


def _with_lens(camera_defaults: Mapping[str, float], projection: Projection) -> dict[str, float]:
    """The scene's default camera with the one lens of ``projection`` (``fov`` or ``view_height``,
    as a keyframe names it); without a lens where the scene has none."""
    out = {k: float(v) for k, v in camera_defaults.items() if k not in ("fov", "fov_deg", "view_height")}
    scene = dict(out)
    if "fov_deg" in camera_defaults or "fov" in camera_defaults:
        scene["fov_deg"] = float(camera_defaults.get("fov_deg", camera_defaults.get("fov", 0.0)))
    if "view_height" in camera_defaults:
        scene["view_height"] = float(camera_defaults["view_height"])
    if "fov_deg" not in scene and "view_height" not in scene:
        return out  # a keyframe without a lens is refused, naming it
    fov, view_height = choose_lens(scene, projection=projection)
    if fov is not None:
        out["fov"] = fov
    else:
        out["view_height"] = float(view_height)  # type: ignore[arg-type]
    return out


def _keyframe(raw: object, where: str, axes: Sequence[AxisLike], defaults: Mapping[str, float]) -> Keyframe:
    if not isinstance(raw, dict):
        raise PathError(f"{where}: must be a JSON object, got {_json_type(raw)}")
    _refuse_unknown_keys(raw, KEYFRAME_KEYS, where)
    if "time" not in raw:
        raise PathError(f"{where}.time: missing")
    time = _number(raw["time"], f"{where}.time")
    if time < 0.0:
        raise PathError(f"{where}.time: must be >= 0, got {time:g}")
    camera = _camera(raw.get("camera", {}), f"{where}.camera", defaults)
    params = _params(raw.get("params", {}), f"{where}.params", axes)
    return Keyframe(time, camera, params)


def _camera(raw: object, where: str, defaults: Mapping[str, float]) -> CameraKey:
    if not isinstance(raw, dict):
        raise PathError(f"{where}: must be a JSON object, got {_json_type(raw)}")
    if "c2w" in raw:
        _refuse_unknown_keys(raw, MATRIX_CAMERA_KEYS, where,
                             "a camera given by c2w takes only c2w and fov or view_height")
        azimuth, elevation, distance = orbit_from_look_at(raw["c2w"], f"{where}.c2w")
        values = {"azimuth": azimuth, "elevation": elevation, "distance": distance}
    else:
        _refuse_unknown_keys(raw, ORBIT_CAMERA_KEYS, where)
        values = {name: _number(raw[name], f"{where}.{name}") for name in ORBIT_CAMERA_KEYS[:3] if name in raw}
    if all(name in raw for name in LENS_KEYS):
        raise PathError(f"{where}: give fov (perspective) or view_height (orthographic), not both")
    lens = next((name for name in LENS_KEYS if name in raw), None)
    if lens is not None:
        values[lens] = _number(raw[lens], f"{where}.{lens}")
    else:
        lens = "view_height" if "view_height" in defaults else "fov"
    for name in (*ORBIT_CAMERA_KEYS[:3], lens):
        if name not in values:
            if name not in defaults:
                raise PathError(f"{where}.{name}: missing, and the scene has no default for it")
            values[name] = float(defaults[name])
    try:
        return CameraKey(values["azimuth"], values["elevation"], values["distance"], values.get("fov"),
                         values.get("view_height"))
    except PathError as exc:  # its message names camera.<field>
        raise PathError(f"{where.removesuffix('.camera')}.{exc}") from None


def orbit_from_look_at(raw: object, where: str) -> tuple[float, float, float]:
    """(azimuth, elevation, distance) of a rigid 4x4 camera-to-world matrix (OpenGL axes: the
    camera looks down its -z) that looks at the origin within ``LOOK_AT_TOLERANCE_DEG``.

    A roll about the viewing axis is not kept: orbit cameras hold the horizon level. At the
    poles, where the position has no azimuth, the azimuth comes from the camera's x axis
    (``orbit_c2w`` makes it ``(cos az, 0, -sin az)``).
    """
    if not (isinstance(raw, list) and len(raw) == 4 and all(isinstance(r, list) and len(r) == 4 for r in raw)):
        raise PathError(f"{where}: must be 4 rows of 4 numbers")
    m = np.array([[_number(v, f"{where}[{i}][{j}]") for j, v in enumerate(row)] for i, row in enumerate(raw)])
    try:
        check_rigid_c2w(m)
    except ValueError as exc:
        raise PathError(f"{where}: not a rigid camera-to-world matrix: {exc}") from None
    position = m[:3, 3]  # [3]
    distance = float(np.linalg.norm(position))
    if distance <= 1e-9:
        raise PathError(f"{where}: the camera sits on the origin it should look at")
    back = position / distance  # [3] from the origin to the camera
    forward = -m[:3, 2] / np.linalg.norm(m[:3, 2])  # [3] the viewing direction
    off = math.degrees(math.acos(max(-1.0, min(1.0, float(-back @ forward)))))
    if off > LOOK_AT_TOLERANCE_DEG:
        raise PathError(f"{where}: the camera looks {off:.2f} degrees away from the origin "
                        f"(at most {LOOK_AT_TOLERANCE_DEG:g} allowed: orbit cameras look at the origin)")
    x, y, z = (float(c) for c in back)
    elevation = math.degrees(math.asin(max(-1.0, min(1.0, y))))
    if math.hypot(x, z) > 1e-9:
        azimuth = math.degrees(math.atan2(x, z))
    else:
        azimuth = math.degrees(math.atan2(-float(m[2, 0]), float(m[0, 0])))
    return azimuth, elevation, distance


def _params(raw: object, where: str, axes: Sequence[AxisLike]) -> dict[str, float]:
    if not isinstance(raw, dict):
        raise PathError(f"{where}: must be a JSON object of name: value, got {_json_type(raw)}")
    by_name = {axis.name: axis for axis in axes}
    unknown = sorted(str(k) for k in raw if k not in by_name)
    if unknown:
        raise PathError(f"{where}.{unknown[0]}: unknown parameter; this scene has {sorted(by_name)}")
    out = {}
    for axis in axes:
        if axis.name not in raw:
            out[axis.name] = float(axis.default)
            continue
        value = _number(raw[axis.name], f"{where}.{axis.name}")
        out[axis.name] = clamp_to_axis(value, axis, f"{where}.{axis.name}")
    return out


def clamp_to_axis(value: float, axis: AxisLike, where: str) -> float:
    """``value`` clamped into the axis range, allowing float32 rounding at the ends (a range read
    from a checkpoint holds 0.1199999973 for 0.12); raises PathError naming ``where`` when it is
    further out."""
    lo, hi = float(axis.min), float(axis.max)
    tol = 1e-6 * max(abs(lo), abs(hi), hi - lo, 1e-30)
    if not lo - tol <= value <= hi + tol:
        raise PathError(f"{where}: must be in [{lo:g}, {hi:g}], got {value:g}")
    return min(max(value, lo), hi)


def _number(value: object, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise PathError(f"{where}: must be a number, got {_json_type(value)} {value!r}")
    try:
        number = float(value)
    except OverflowError:  # an integer beyond float range
        number = math.inf
    if not math.isfinite(number):
        raise PathError(f"{where}: must be a finite number, got {number}")
    return number


def _choice(value: object, allowed: tuple[str, ...], where: str) -> str:
    if not isinstance(value, str) or value not in allowed:
        raise PathError(f"{where}: must be one of {list(allowed)}, got {value!r}")
    return value


def _refuse_unknown_keys(raw: dict, allowed: tuple[str, ...], where: str, hint: str = "") -> None:
    unknown = sorted(str(k) for k in raw if k not in allowed)
    if unknown:
        prefix = "" if where == "path" else f"{where}."
        raise PathError(f"{prefix}{unknown[0]}: unknown key; {hint or 'allowed: ' + ', '.join(allowed)}")


def _json_type(value: object) -> str:
    names = {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null"}
    return names.get(type(value), type(value).__name__)
