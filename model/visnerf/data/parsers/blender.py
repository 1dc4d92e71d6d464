"""Parser for NeRF-Blender style ``transforms_*.json`` datasets (also D-NeRF and nerfstudio keys).

Accepted: ``camera_angle_x`` or nerfstudio intrinsics (``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``,
``h``); ``frames[].params`` (K numbers) or a D-NeRF ``frames[].time`` (one axis named ``time``);
optional ``param_names``, ``white_background`` (default true), ``bbox``, ``scene`` ({title, kind});
``file_path`` with or without extension; RGBA images composited on the background.

A bad dataset is refused with a :class:`DatasetError` naming the split file, the frame(s) and the
problem, before any image is decoded where the JSON alone shows it: frames missing or not a list,
a frame without ``file_path``/``transform_matrix``, a pose that is not a finite rigid 4x4 matrix,
the same image used by two frames, parameter lists of different lengths or non-finite values,
missing or undecodable images, images of different sizes, a bad ``bbox``.
"""

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from visnerf.data.cameras import Intrinsics
from visnerf.data.errors import DatasetError
from visnerf.data.images import load_images
from visnerf.data.scene import SceneData, axes_from_values, view_ids_from_poses

__all__ = ["DatasetError", "ParsedSplit", "check_rigid", "load_transforms", "read_transforms"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".webp", ".PNG", ".JPG")

RIGID_TOLERANCE = 1e-3
"""Largest accepted entry of |R^T R - I| and |last row - (0, 0, 0, 1)| of a pose.

Exported datasets carry float noise around 1e-7; this is the tolerance ``check_rigid_c2w`` applies to
poses sent to the server, so a model trained on a dataset can be viewed from the dataset's own poses.
"""

def _frame_label(index: int, frame: Any) -> str:
    """``frame 3 (./train/r_3)``: how messages name a frame (without the path when it has none)."""
    if isinstance(frame, dict) and "file_path" in frame:
        return f"frame {index} ({frame['file_path']})"
    return f"frame {index}"


def _read_meta(path: Path) -> dict[str, Any]:
    """The split file's JSON object; refused when missing, not JSON, or not an object."""
    try:
        meta = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"transforms file {path} does not exist") from None
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path} is not valid JSON: {exc}") from None
    if not isinstance(meta, dict):
        raise DatasetError(f"{path} must hold a JSON object with a 'frames' list, got {type(meta).__name__}")
    return meta


def _frames(meta: dict[str, Any], path: Path) -> list[dict[str, Any]]:
    """``meta["frames"]``: checked to be a non-empty list of JSON objects."""
    frames = meta.get("frames")
    if frames is None:
        raise DatasetError(f"{path} has no frames (no 'frames' key)")
    if not isinstance(frames, list):
        raise DatasetError(f"{path}: 'frames' must be a list of frames, got {type(frames).__name__}")
    if not frames:
        raise DatasetError(f"{path} has no frames (the 'frames' list is empty)")
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise DatasetError(f"{path}: frame {i} must be a JSON object, got {type(frame).__name__}")
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise DatasetError(f"{path}: {_frame_label(i, frame)} lacks {key!r}")
    return frames


def _pose_matrix(frame: dict[str, Any], label: str) -> np.ndarray:
    """The frame's ``transform_matrix`` as a float64 array; checked to be a finite 4x4 matrix."""
    try:
        matrix = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{label}: transform_matrix is not a 4x4 matrix of numbers") from None
    if matrix.shape != (4, 4):
        raise DatasetError(f"{label}: transform_matrix is not a 4x4 matrix (shape {list(matrix.shape)})")
    if not np.all(np.isfinite(matrix)):
        raise DatasetError(f"{label}: transform_matrix has non-finite entries (NaN or infinity)")
    return matrix


def check_rigid(c2w: np.ndarray, labels: list[str], tol: float = RIGID_TOLERANCE) -> None:
    """Every camera-to-world matrix is rigid: last row (0, 0, 0, 1), rotation orthonormal with det +1.

    A uniform scale is refused too. The ray generator (``cameras.rays_from_pixels``) normalises ray
    directions, so a scale would not bend rays, but ``cameras.project_points`` (used by the carving
    of empty space) inverts the rotation by transposing it and so scales depths, and the server's
    ``check_rigid_c2w`` refuses scaled poses. A scaled pose is more likely a units mistake than intent.
    """
    row_error = np.abs(c2w[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=-1)
    rotation = c2w[:, :3, :3]
    gram = np.einsum("nji,njk->nik", rotation, rotation)
    ortho_error = np.abs(gram - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rotation)
    for i, label in enumerate(labels):
        if row_error[i] > tol:
            raise DatasetError(f"{label}: transform_matrix last row is {c2w[i, 3].tolist()}, expected [0, 0, 0, 1]")
        if ortho_error[i] > tol:
            lengths = ", ".join(f"{v:.4g}" for v in np.linalg.norm(rotation[i], axis=0))
            raise DatasetError(
                f"{label}: transform_matrix rotation is not orthonormal (max |R^T R - I| = {ortho_error[i]:.3g}, "
                f"column lengths {lengths}); poses must be rigid, without scale or shear"
            )
        if det[i] < 0:
            raise DatasetError(
                f"{label}: transform_matrix rotation has determinant {det[i]:.3g} (a mirror), expected +1"
            )


def _frame_params(frame: dict[str, Any], label: str) -> list[float]:
    """The frame's parameter values: ``params`` (a list of numbers), then D-NeRF ``time`` where the
    frame has it (``_time_column`` folds it into a ``params`` column that repeats it)."""
    values: list[Any] = []
    if "params" in frame:
        values = frame["params"]
        if not isinstance(values, list):
            raise DatasetError(f"{label}: params must be a list of numbers")
        values = list(values)
    if "time" in frame:
        values.append(frame["time"])
    try:
        return [float(v) for v in values]
    except (TypeError, ValueError):
        raise DatasetError(f"{label}: params must be numbers, got {values!r}") from None


def _check_param_counts(params: list[list[float]], labels: list[str]) -> None:
    """Every frame has as many parameter values as the first; names the first frame that differs."""
    k = len(params[0])
    for i, values in enumerate(params):
        if len(values) != k:
            raise DatasetError(
                f"frames disagree on the number of parameters: {labels[i]} has {len(values)}, "
                f"{labels[0]} has {k}"
            )


def _check_param_values(values: np.ndarray, labels: list[str]) -> None:
    """Every parameter value is finite; names the first frame holding NaN or infinity."""
    bad = np.nonzero(~np.all(np.isfinite(values), axis=1))[0]
    if bad.size:
        i = int(bad[0])
        raise DatasetError(
            f"{labels[i]}: parameter values must be finite, got {values[i].tolist()} "
            f"({bad.size} frame(s) hold non-finite values)"
        )


def _resolve_image(root: Path, file_path: str, label: str) -> Path:
    """The image file of ``file_path`` under ``root``, as given or with one of IMAGE_EXTENSIONS."""
    candidate = (root / file_path).resolve()
    if candidate.is_file():
        return candidate
    for ext in IMAGE_EXTENSIONS:
        with_ext = candidate.with_name(candidate.name + ext)
        if with_ext.is_file():
            return with_ext
    raise DatasetError(f"{label}: image not found under {root} (tried the extensions {IMAGE_EXTENSIONS})")


def _check_unique_images(image_paths: list[Path], labels: list[str]) -> None:
    """No image is used by two frames (the same file, however its file_path is spelled)."""
    first_use: dict[Path, int] = {}
    for i, image in enumerate(image_paths):
        j = first_use.setdefault(image, i)
        if j != i:
            raise DatasetError(f"{labels[j]} and {labels[i]} use the same image {image}: a frame appears twice")


def _intrinsics(meta: dict[str, Any], width: int, height: int) -> Intrinsics:
    """The camera intrinsics at the images' size (``_check_intrinsics_given`` ran before)."""
    if "fl_x" in meta:
        w, h = int(meta.get("w", width)), int(meta.get("h", height))
        fx = float(meta["fl_x"])
        fy = float(meta.get("fl_y", fx))
        intr = Intrinsics(w, h, fx, fy, float(meta.get("cx", w / 2)), float(meta.get("cy", h / 2)))
        return intr if (w, h) == (width, height) else intr.scaled(width, height)
    if "camera_angle_x" in meta:
        return Intrinsics.from_fov(width, height, float(meta["camera_angle_x"]))
    raise DatasetError("transforms file gives neither camera_angle_x nor fl_x")


def _check_intrinsics_given(meta: dict[str, Any]) -> None:
    """The split gives a focal length: ``camera_angle_x`` or nerfstudio's ``fl_x``."""
    if "fl_x" not in meta and "camera_angle_x" not in meta:
        raise DatasetError("transforms file gives neither camera_angle_x nor fl_x")


def _bbox(meta: dict[str, Any]) -> torch.Tensor | None:
    """The optional ``bbox``: checked to be [[x0, y0, z0], [x1, y1, z1]] with x1 > x0 etc."""
    if "bbox" not in meta:
        return None
    try:
        box = np.asarray(meta["bbox"], dtype=np.float32)
    except (TypeError, ValueError):
        box = np.zeros(0, dtype=np.float32)
    if box.shape != (2, 3) or not np.all(box[1] > box[0]):
        raise DatasetError("bbox must be [[x0,y0,z0],[x1,y1,z1]] with x1>x0 etc.")
    return torch.from_numpy(box)


def _in_file(path: Path, exc: DatasetError) -> DatasetError:
    """``exc`` with its message prefixed by the split file."""
    return DatasetError(f"{path}: {exc}")


def _poses(frames: list[dict[str, Any]], labels: list[str]) -> np.ndarray:
    """The frames' camera-to-world matrices, [n, 4, 4] float64, checked finite and rigid."""
    c2w = np.stack([_pose_matrix(frame, label) for frame, label in zip(frames, labels, strict=True)])
    check_rigid(c2w, labels)
    return c2w


def _param_table(frames: list[dict[str, Any]], labels: list[str]) -> np.ndarray:
    """The frames' parameter values, [n, K] float64 (``params``, then ``time``), checked to have one
    length and finite values."""
    params = [_frame_params(frame, label) for frame, label in zip(frames, labels, strict=True)]
    _check_param_counts(params, labels)
    values = np.asarray(params, dtype=np.float64).reshape(len(frames), len(params[0]))
    _check_param_values(values, labels)
    return values


def _time_column(frames: list[dict[str, Any]], values: np.ndarray) -> int | None:
    """The column of ``params`` that equals ``time`` in every frame, when frames carry both."""
    if not ("time" in frames[0] and "params" in frames[0]):
        return None
    time = values[:, -1]
    same = [j for j in range(values.shape[1] - 1) if np.array_equal(values[:, j], time)]
    return same[0] if same else None


def _param_names(
    meta: dict[str, Any], frames: list[dict[str, Any]], values: np.ndarray
) -> tuple[list[str], np.ndarray]:
    """Names of the parameter columns and the columns kept: ``param_names`` for ``params`` (``p0``,
    ``p1``... without it) and ``time`` for a D-NeRF time; a time that repeats a ``params`` column
    names that column instead of adding one. ``param_names`` may also name the time column."""
    k = values.shape[1]
    has_time, has_params = "time" in frames[0], "params" in frames[0]
    n_params = k - 1 if has_time else k
    given = meta.get("param_names")
    if given is not None and not (isinstance(given, list) and all(isinstance(n, str) for n in given)):
        raise DatasetError("param_names must be a list of strings")
    names = list(given) if given else [f"p{j}" for j in range(n_params)]
    if has_time and len(names) == n_params:
        names.append("time")
    if len(names) != k:
        raise DatasetError(f"param_names has {len(names)} names for {n_params} parameters"
                           + (" and a time" if has_time and has_params else ""))
    twin = _time_column(frames, values)
    if twin is not None:
        if not given:
            names[twin] = "time"
        names, values = names[:-1], values[:, :-1]
    if len(set(names)) != len(names):
        raise DatasetError(f"parameter names must be unique, got {names}")
    return names, values


def _image_paths(root: Path, frames: list[dict[str, Any]], labels: list[str]) -> list[Path]:
    """The frames' image files, checked to exist and to be used by one frame each."""
    paths = [_resolve_image(root, str(frame["file_path"]), label) for frame, label in zip(frames, labels, strict=True)]
    _check_unique_images(paths, labels)
    return paths


@dataclass(frozen=True)
class ParsedSplit:
    """One split as read: the frames, and the parameter table before constant columns are dropped."""

    scene: SceneData
    param_names: tuple[str, ...]
    """Every parameter column's name, constant ones included."""
    param_values: np.ndarray
    """[n, j] float64 raw values, one column per name."""
    notes: tuple[str, ...] = ()
    """How the source's fields were read (which column became what, and why)."""


def read_transforms(path: str | Path, max_workers: int = 2) -> ParsedSplit:
    """Read one split (``transforms_<split>.json``): its frames and its full parameter table.

    Everything the JSON alone can show is checked before any image is decoded; every refusal is a
    DatasetError naming the split file, the frame(s) concerned and the problem.
    """
    path = Path(path)
    meta = _read_meta(path)
    frames = _frames(meta, path)
    root = path.parent
    labels = [_frame_label(i, frame) for i, frame in enumerate(frames)]
    white = bool(meta.get("white_background", True))
    background = np.array([1.0, 1.0, 1.0] if white else [0.0, 0.0, 0.0], dtype=np.float32)
    try:
        c2w = _poses(frames, labels)
        names, values = _param_names(meta, frames, _param_table(frames, labels))
        image_paths = _image_paths(root, frames, labels)
        _check_intrinsics_given(meta)
        bbox = _bbox(meta)
        images = load_images(image_paths, labels, background, max_workers)
    except DatasetError as exc:
        raise _in_file(path, exc) from None
    keep, axes = axes_from_values(names, values)
    height, width = images.shape[1:3]
    scene = meta.get("scene", {}) if isinstance(meta.get("scene"), dict) else {}
    data = SceneData(
        images=images,
        c2w=torch.from_numpy(c2w).float(),
        intrinsics=_intrinsics(meta, width, height),
        params=torch.from_numpy(values[:, keep]).float() if keep else torch.zeros(len(frames), 0),
        param_axes=axes,
        view_ids=torch.from_numpy(view_ids_from_poses(c2w)),
        background=tuple(float(x) for x in background),  # type: ignore[arg-type]
        bbox=bbox,
        title=str(scene.get("title", root.name)),
        kind=str(scene.get("kind", "dvr")),
        file_paths=tuple(str(p) for p in image_paths),
        source=str(path),
    )
    return ParsedSplit(data, tuple(names), values)


def load_transforms(path: str | Path, max_workers: int = 2) -> SceneData:
    """The frames of one split (``transforms_<split>.json``); ``read_transforms`` gives its table too."""
    return read_transforms(path, max_workers).scene
