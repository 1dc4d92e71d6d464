"""Checks of a checkpoint's JSON metadata, made on the parsed document before anything is built
from it (``CheckpointMeta.from_json``). Every refusal raises ``MetadataError`` naming the field as
a path into the document: ``param_axes[1].default``, ``background[2]``, ``camera.fov_deg``.

The configurations (``field``, ``render``) are judged by their own checks (``visnerf.config``).
"""

import json
import math
from typing import Any

SCENE_KINDS = ("dvr", "ir")
"""What a scene's images show: direct volume rendering or isosurfaces."""

RESERVED_PARAM_NAMES = frozenset(
    {"azimuth", "elevation", "distance", "c2w", "fov_deg", "projection", "view_height", "width", "height", "quality",
     "format", "seq"}
)
"""Names of the camera, image and message fields of a render request. The render server's GET
query gives a scene's parameters by their own names beside these, so no axis may take one."""

MAX_AXIS_NAME_CHARS = 64
MAX_IMAGE_SIDE = 65536
"""Largest training image width or height a checkpoint may state."""
MAX_OCCUPANCY_SIDE = 4096
"""Largest occupancy grid size along one axis."""

CAMERA_LIMITS: dict[str, tuple[float, float, bool]] = {
    "azimuth": (-360.0, 360.0, False),
    "elevation": (-90.0, 90.0, False),
    "distance": (0.0, 1e6, True),
    "fov_deg": (0.0, 180.0, True),
    "view_height": (0.0, 1e6, True),
}
"""The default camera's values: (low, high, whether the ends are excluded); the render request's
bounds. ``distance`` may be 1e6, ``fov_deg`` not 180. ``view_height`` (world units) marks an
orthographic camera, ``fov_deg`` a perspective one: a camera has one or the other."""


class MetadataError(ValueError):
    """A field of the metadata is missing, of the wrong type or out of its range; names the field."""


class _NonFinite:
    """Stands in for a NaN or infinity while parsing, so that the walk can name where it was."""

    def __init__(self, text: str) -> None:
        self.text = text


def _parse_float(text: str) -> float | _NonFinite:
    value = float(text)
    return value if math.isfinite(value) else _NonFinite(text)  # 1e999 parses as inf


def parse_metadata_json(text: str) -> Any:
    """The JSON document, refusing NaN, Infinity and overflowing numbers with the field named
    (Python's ``json`` accepts all three)."""
    try:
        data = json.loads(text, parse_constant=_NonFinite, parse_float=_parse_float)
    except ValueError as exc:  # JSONDecodeError, and integers over Python's digit limit
        raise MetadataError(f"not valid JSON: {exc}") from None
    where = _non_finite_path(data, "")
    if where is not None:
        path, value = where
        raise MetadataError(f"{path or 'the document'} is {value.text}: every number must be finite")
    return data


def _non_finite_path(value: Any, path: str) -> tuple[str, _NonFinite] | None:
    if isinstance(value, _NonFinite):
        return path, value
    if isinstance(value, dict):
        children = ((f"{path}.{k}" if path else str(k), v) for k, v in value.items())
    elif isinstance(value, list):
        children = ((f"{path}[{i}]", v) for i, v in enumerate(value))
    else:
        return None
    for child_path, child in children:
        found = _non_finite_path(child, child_path)
        if found is not None:
            return found
    return None


# --- values -------------------------------------------------------------------------------------


def _number(path: str, value: Any) -> float:
    """A finite JSON number (an integer counts; true and false do not)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise MetadataError(f"{path} must be a number, got {value!r}")
    try:
        number = float(value)
    except OverflowError:
        number = math.inf
    if not math.isfinite(number):
        raise MetadataError(f"{path} must be a finite number, got {value!r}")
    return number


def _numbers(path: str, value: Any, length: int | None = None) -> list[float]:
    if not isinstance(value, list):
        raise MetadataError(f"{path} must be a list of numbers, got {value!r}")
    if length is not None and len(value) != length:
        raise MetadataError(f"{path} must hold {length} numbers, got {len(value)}")
    return [_number(f"{path}[{i}]", v) for i, v in enumerate(value)]


def _whole(path: str, value: Any, least: int, most: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not least <= value <= most:
        raise MetadataError(f"{path} must be a whole number in [{least}, {most}], got {value!r}")
    return value


def _within(path: str, value: float, low: float, high: float, open_ends: bool = False) -> None:
    inside = low < value < high if open_ends else low <= value <= high
    if not inside:
        ends = f"({low:g}, {high:g})" if open_ends else f"[{low:g}, {high:g}]"
        raise MetadataError(f"{path} {value!r} is outside {ends}")


def _object(path: str, value: Any) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise MetadataError(f"{path} must be a JSON object, got {type(value).__name__}")
    return value


def _required(data: dict[str, Any], key: str, parent: str = "") -> Any:
    if key not in data:
        raise MetadataError(f"{parent}.{key} is missing" if parent else f"{key} is missing")
    return data[key]


# --- parameter axes -----------------------------------------------------------------------------


def _axis_name(path: str, value: Any, seen: set[str]) -> str:
    if not isinstance(value, str) or not value or len(value) > MAX_AXIS_NAME_CHARS:
        raise MetadataError(f"{path} must be a name of 1 to {MAX_AXIS_NAME_CHARS} characters, got {value!r}")
    if not value.isprintable() or value != value.strip():
        raise MetadataError(f"{path} {value!r} has control characters or surrounding spaces")
    if value in RESERVED_PARAM_NAMES:
        raise MetadataError(
            f"{path} {value!r} is the name of a render request field ({', '.join(sorted(RESERVED_PARAM_NAMES))})"
        )
    if value in seen:
        raise MetadataError(f"{path} {value!r} names a second axis of that name")
    seen.add(value)
    return value


def _check_axis_values(path: str, low: float, high: float, default: float, values: list[float]) -> None:
    if not values:
        raise MetadataError(f"{path}.values must list at least one training value")
    if low > high:
        raise MetadataError(f"{path}.min {low!r} is above {path}.max {high!r}")
    if len(values) > 1 and not low < high:
        raise MetadataError(f"{path}.min must be below {path}.max for an axis of {len(values)} values, "
                            f"both are {low!r}")
    _within(f"{path}.default", default, low, high)
    for i, value in enumerate(values):
        _within(f"{path}.values[{i}]", value, low, high)
        if i and not value > values[i - 1]:
            raise MetadataError(f"{path}.values must increase strictly: [{i - 1}] {values[i - 1]!r}, [{i}] {value!r}")


def check_param_axes(value: Any) -> None:
    if not isinstance(value, list):
        raise MetadataError(f"param_axes must be a list of axes, got {value!r}")
    seen: set[str] = set()
    for i, axis in enumerate(value):
        path = f"param_axes[{i}]"
        axis = _object(path, axis)
        _axis_name(f"{path}.name", _required(axis, "name", path), seen)
        low, high, default = (_number(f"{path}.{k}", _required(axis, k, path)) for k in ("min", "max", "default"))
        _check_axis_values(path, low, high, default, _numbers(f"{path}.values", _required(axis, "values", path)))


# --- the scene ----------------------------------------------------------------------------------


def check_bbox(value: Any) -> None:
    if not isinstance(value, list) or len(value) != 2:
        raise MetadataError(f"bbox must be two corners [[x, y, z], [x, y, z]], got {value!r}")
    low, high = (_numbers(f"bbox[{i}]", corner, 3) for i, corner in enumerate(value))
    for k in range(3):
        if not low[k] < high[k]:
            raise MetadataError(f"bbox[0][{k}] {low[k]!r} is not below bbox[1][{k}] {high[k]!r}")


def check_background(value: Any) -> None:
    for i, channel in enumerate(_numbers("background", value, 3)):
        _within(f"background[{i}]", channel, 0.0, 1.0)


def check_camera(value: Any) -> None:
    for key, entry in _object("camera", value).items():
        if key not in CAMERA_LIMITS:
            raise MetadataError(f"camera.{key} is not a camera value (known: {', '.join(CAMERA_LIMITS)})")
        low, high, open_ends = CAMERA_LIMITS[key]
        _within(f"camera.{key}", _number(f"camera.{key}", entry), low, high, open_ends)
    if "fov_deg" in value and "view_height" in value:
        raise MetadataError("camera has both fov_deg (perspective) and view_height (orthographic)")


def check_scene_fields(data: dict[str, Any]) -> None:
    """Image size, kind, title, occupancy grid size and the free-form objects."""
    for key in ("image_width", "image_height"):
        _whole(key, _required(data, key), 1, MAX_IMAGE_SIDE)
    kind = data.get("kind", "dvr")
    if kind not in SCENE_KINDS:
        raise MetadataError(f"kind must be one of {', '.join(SCENE_KINDS)}, got {kind!r}")
    if not isinstance(data.get("title", ""), str):
        raise MetadataError(f"title must be a string, got {data['title']!r}")
    occupancy = data.get("occupancy_resolution")
    if occupancy is not None:
        if not isinstance(occupancy, list) or len(occupancy) != 3:
            raise MetadataError(f"occupancy_resolution must be three sizes, got {occupancy!r}")
        for i, size in enumerate(occupancy):
            _whole(f"occupancy_resolution[{i}]", size, 1, MAX_OCCUPANCY_SIDE)
    _object("field", _required(data, "field"))
    for key in ("render", "provenance"):
        _object(key, data.get(key, {}))


def check_metadata(data: Any) -> None:
    """Every check of this module on a parsed metadata document; the first problem raises."""
    data = _object("the metadata", data)
    check_param_axes(_required(data, "param_axes"))
    check_bbox(_required(data, "bbox"))
    check_background(data.get("background", [1.0, 1.0, 1.0]))
    check_camera(data.get("camera", {}))
    check_scene_fields(data)
