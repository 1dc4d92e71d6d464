"""Parser for NeRF-Blender style ``transforms_*.json`` datasets (also D-NeRF and nerfstudio keys).

Accepted: ``camera_angle_x`` or nerfstudio intrinsics (``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``,
``h``); ``frames[].params`` (K numbers) or a D-NeRF ``frames[].time`` (one axis named ``time``);
optional ``param_names``, ``white_background`` (default true), ``bbox``, ``scene`` ({title, kind});
``file_path`` with or without extension; RGBA images composited on the background.
"""

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from visnerf.data.cameras import Intrinsics
from visnerf.data.scene import SceneData, axes_from_values, view_ids_from_poses

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".webp", ".PNG", ".JPG")


class DatasetError(ValueError):
    """The dataset cannot be read; the message names the file and the problem."""


def _resolve_image(root: Path, file_path: str) -> Path:
    candidate = (root / file_path).resolve()
    if candidate.is_file():
        return candidate
    for ext in IMAGE_EXTENSIONS:
        with_ext = candidate.with_name(candidate.name + ext)
        if with_ext.is_file():
            return with_ext
    raise DatasetError(f"image {file_path!r} not found under {root} (tried the extensions {IMAGE_EXTENSIONS})")


def _load_rgb(path: Path, background: np.ndarray) -> np.ndarray:
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in ("RGBA", "LA") or (im.mode == "P" and "transparency" in im.info):
                rgba = np.asarray(im.convert("RGBA"), dtype=np.float32) / 255.0
                rgb = rgba[..., :3] * rgba[..., 3:] + background * (1.0 - rgba[..., 3:])
                return np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
            return np.asarray(im.convert("RGB"), dtype=np.uint8)
    except OSError as exc:
        raise DatasetError(f"cannot decode image {path}: {exc}") from None


def _intrinsics(meta: dict[str, Any], width: int, height: int) -> Intrinsics:
    if "fl_x" in meta:
        w, h = int(meta.get("w", width)), int(meta.get("h", height))
        fx = float(meta["fl_x"])
        fy = float(meta.get("fl_y", fx))
        intr = Intrinsics(w, h, fx, fy, float(meta.get("cx", w / 2)), float(meta.get("cy", h / 2)))
        return intr if (w, h) == (width, height) else intr.scaled(width, height)
    if "camera_angle_x" in meta:
        return Intrinsics.from_fov(width, height, float(meta["camera_angle_x"]))
    raise DatasetError("transforms file gives neither camera_angle_x nor fl_x")


def _frame_params(frame: dict[str, Any], index: int) -> list[float]:
    if "params" in frame:
        values = frame["params"]
        if not isinstance(values, list):
            raise DatasetError(f"frame {index}: params must be a list of numbers")
        return [float(v) for v in values]
    if "time" in frame:
        return [float(frame["time"])]
    return []


def load_transforms(path: str | Path, max_workers: int = 2) -> SceneData:
    """Load one split (``transforms_<split>.json``) into a SceneData."""
    path = Path(path)
    try:
        meta = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"transforms file {path} does not exist") from None
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path} is not valid JSON: {exc}") from None
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{path} has no frames")
    root = path.parent
    white = bool(meta.get("white_background", True))
    background = np.array([1.0, 1.0, 1.0] if white else [0.0, 0.0, 0.0], dtype=np.float32)

    c2w = np.zeros((len(frames), 4, 4), dtype=np.float64)
    params_list = []
    image_paths = []
    for i, frame in enumerate(frames):
        try:
            matrix = np.asarray(frame["transform_matrix"], dtype=np.float64)
            image_paths.append(_resolve_image(root, str(frame["file_path"])))
        except KeyError as exc:
            raise DatasetError(f"{path}: frame {i} lacks {exc.args[0]!r}") from None
        if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
            raise DatasetError(f"{path}: frame {i} transform_matrix is not a finite 4x4 matrix")
        c2w[i] = matrix
        params_list.append(_frame_params(frame, i))
    k = len(params_list[0])
    if any(len(p) != k for p in params_list):
        raise DatasetError(f"{path}: frames disagree on the number of parameters")
    values = np.asarray(params_list, dtype=np.float64).reshape(len(frames), k)
    if not np.all(np.isfinite(values)):
        raise DatasetError(f"{path}: parameter values must be finite")
    names = list(meta.get("param_names") or (["time"] if "time" in frames[0] else [f"p{j}" for j in range(k)]))
    if len(names) != k:
        raise DatasetError(f"{path}: param_names has {len(names)} names for {k} parameters")
    keep, axes = axes_from_values(names, values)

    with ThreadPoolExecutor(max_workers=max_workers) as pool:
        images = list(pool.map(lambda p: _load_rgb(p, background), image_paths))
    shapes = {im.shape for im in images}
    if len(shapes) != 1:
        raise DatasetError(f"{path}: images differ in size {sorted(shapes)}")
    height, width = images[0].shape[:2]
    stacked = torch.from_numpy(np.stack(images))
    del images

    bbox = None
    if "bbox" in meta:
        box = np.asarray(meta["bbox"], dtype=np.float32)
        if box.shape != (2, 3) or not np.all(box[1] > box[0]):
            raise DatasetError(f"{path}: bbox must be [[x0,y0,z0],[x1,y1,z1]] with x1>x0 etc.")
        bbox = torch.from_numpy(box)
    scene = meta.get("scene", {}) if isinstance(meta.get("scene"), dict) else {}
    return SceneData(
        images=stacked,
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


def load_dataset(folder: str | Path, split: str = "train") -> SceneData:
    """Load ``folder/transforms_<split>.json``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"dataset folder {folder} does not exist")
    return load_transforms(folder / f"transforms_{split}.json")
