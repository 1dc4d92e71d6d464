"""Parser for Cinema databases (``NAME.cdb/data.csv``, Spec D) as ParaView, Ascent and pycinema write them.

Columns: the image column (the first ``FILE*`` column of PNG, JPEG or pycinema ``.h5`` files), the
camera's angle columns (``phi``/``azimuth``, ``theta``/``elevation``, any case), and every other
numeric column a parameter (constant ones dropped, as in every dataset); text columns are kept
out. Cameras come from the images' own metadata (pycinema), else from the angles under a
convention (``cinema_cameras``), detected where the database says so (a ``producer`` column
naming ParaView, Ascent's ``info.json``) or named. The rows are checked whole (values, files,
cameras) before any image is decoded; every refusal names the row and column concerned.
"""

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from visnerf.data.cameras import Intrinsics, frame_c2w
from visnerf.data.errors import DatasetError
from visnerf.data.images import DECODE_ERRORS, composite, load_images, load_rgb
from visnerf.data.parsers.blender import ParsedSplit, check_rigid
from visnerf.data.parsers.cinema_cameras import (
    CAMERA_FILE,
    CinemaCamera,
    Convention,
    ascent_c2w,
    ascent_centre_distance,
    paraview_c2w,
    paraview_focal_distance,
    read_camera_file,
)
from visnerf.data.parsers.cinema_table import CinemaTable, read_table
from visnerf.data.scene import SceneData, axes_from_values, view_ids_from_poses

TABLE_FILE = "data.csv"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".h5")
PHI_NAMES = ("phi", "azimuth")
THETA_NAMES = ("theta", "elevation")
LENS_TOLERANCE = 1e-6
"""Largest relative difference between two images' view heights or angles: one lens for all."""


def is_cinema_database(path: str | Path) -> bool:
    """A folder holding ``data.csv`` (or that file itself)."""
    path = Path(path)
    return (path / TABLE_FILE).is_file() or (path.name == TABLE_FILE and path.is_file())


def database_folder(path: str | Path) -> Path:
    path = Path(path)
    return path.parent if path.name == TABLE_FILE else path


@dataclass(frozen=True)
class H5Image:
    """What a pycinema ``.h5`` image holds that the parser uses."""

    rgba: np.ndarray
    """uint8 [h, w, 4]."""
    depth: np.ndarray | None
    """float32 [h, w], NaN where nothing was hit."""
    c2w: np.ndarray
    lens: tuple[str, float]
    """("view_height", world units) or ("angle", vertical degrees)."""


def _h5_meta(path: Path, label: str) -> dict[str, np.ndarray]:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            group = f.get("meta")
            if group is None:
                raise DatasetError(f"{label}: {path.name} has no 'meta' group: not a pycinema image")
            return {k: np.squeeze(np.asarray(group[k])) for k in group}
    except (OSError, KeyError) as exc:
        raise DatasetError(f"{label}: cannot read {path} as HDF5: {exc}") from None


def _h5_camera(meta: dict[str, np.ndarray], label: str) -> tuple[np.ndarray, tuple[str, float]]:
    """Pose and lens from pycinema metadata; refused when a field is missing or degenerate."""
    missing = [k for k in ("CameraPos", "CameraDir", "CameraUp") if k not in meta]
    if missing:
        raise DatasetError(f"{label}: the image's metadata lacks {missing}")
    try:
        pos, direction, up = (np.asarray(meta[k], dtype=np.float64).reshape(3)
                              for k in ("CameraPos", "CameraDir", "CameraUp"))
        c2w = frame_c2w(pos, direction, up, label)
    except ValueError as exc:  # frame_c2w's message names the row
        raise DatasetError(str(exc)) from None
    if "CameraHeight" in meta:
        value, kind = float(meta["CameraHeight"]), "view_height"
    elif "CameraAngle" in meta:
        value, kind = float(meta["CameraAngle"]), "angle"
    else:
        raise DatasetError(f"{label}: the image's metadata has neither CameraHeight (orthographic) nor "
                           "CameraAngle (perspective)")
    if not (math.isfinite(value) and value > 0 and (kind == "view_height" or value < 180)):
        key = "CameraHeight" if kind == "view_height" else "CameraAngle"
        raise DatasetError(f"{label}: {key} {value} is not usable")
    return c2w, (kind, value)


def _h5_pixels(path: Path, background: np.ndarray, label: str) -> tuple[np.ndarray, np.ndarray | None]:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            channels = f.get("channels")
            if channels is None or "rgba" not in channels:
                present = sorted(channels) if channels is not None else []
                raise DatasetError(f"{label}: {path.name} has no channels/rgba (channels: {present}); "
                                   "images of a scalar channel alone are not supported")
            rgba = np.asarray(channels["rgba"])
            depth_key = next((k for k in ("depth", "Depth") if k in channels), None)
            depth = None if depth_key is None else np.asarray(channels[depth_key], dtype=np.float32)
    except OSError as exc:
        raise DatasetError(f"{label}: cannot read {path} as HDF5: {exc}") from None
    if rgba.ndim != 3 or rgba.shape[2] not in (3, 4):
        raise DatasetError(f"{label}: channels/rgba has shape {list(rgba.shape)}, expected [h, w, 4]")
    if rgba.dtype != np.uint8:
        levels = 255.0 if rgba.max() <= 1.0 else 1.0
        rgba = np.clip(np.asarray(rgba, dtype=np.float32) * levels + 0.5, 0, 255).astype(np.uint8)
    rgb = composite(rgba, background) if rgba.shape[2] == 4 else rgba
    if depth is not None:
        depth = np.squeeze(depth)
        if depth.shape != rgb.shape[:2]:
            raise DatasetError(f"{label}: the depth channel is {list(depth.shape)}, the colour {list(rgb.shape[:2])}")
        depth = np.where(np.isfinite(depth), depth, np.nan).astype(np.float32)
    return rgb, depth


def _image_column(table: CinemaTable) -> str:
    files = table.file_columns()
    if not files:
        raise DatasetError(f"{table.path}: no FILE column (a Cinema table names its images in a column "
                           f"named FILE or starting with FILE; columns: {list(table.columns)})")
    for name in files:
        first = next((v for v in table.strings(name) if v), "")
        if Path(first).suffix.lower() in IMAGE_SUFFIXES:
            return name
    raise DatasetError(f"{table.path}: no FILE column holds images ({', '.join(IMAGE_SUFFIXES)}); "
                       f"FILE columns: {list(files)}")


def _image_paths(table: CinemaTable, column: str, folder: Path) -> list[Path]:
    paths: list[Path] = []
    seen: dict[Path, int] = {}
    for i, text in enumerate(table.strings(column)):
        where = f"{table.path}: row {i + 1}, column {column!r}"
        if text == "":
            raise DatasetError(f"{where}: the image file is missing")
        if "://" in text:
            raise DatasetError(f"{where}: {text!r} is a URI; only files inside the database folder are read")
        path = (folder / text).resolve()
        if Path(text).suffix.lower() not in IMAGE_SUFFIXES:
            raise DatasetError(f"{where}: {text!r} is not a PNG, JPEG or pycinema .h5 image")
        if not path.is_file():
            raise DatasetError(f"{where}: image {text!r} not found in {folder}")
        j = seen.setdefault(path, i)
        if j != i:
            raise DatasetError(f"{where}: image {text!r} is also row {j + 1}'s: a row appears twice")
        paths.append(path)
    return paths


def _detect(table: CinemaTable, folder: Path, paths: list[Path]) -> tuple[Convention | None, str]:
    """The convention the database itself declares, and how it was told."""
    if all(p.suffix.lower() == ".h5" for p in paths):
        return "pycinema", "the images are pycinema .h5 files with their cameras"
    producer = table.find("producer")
    if producer is not None and any("paraview" in v.lower() for v in table.strings(producer)):
        return "paraview", f"the {producer!r} column names ParaView"
    info = folder / "info.json"
    if info.is_file():
        try:
            pattern = str(json.loads(info.read_text()).get("name_pattern", ""))
        except (json.JSONDecodeError, UnicodeDecodeError, AttributeError):
            pattern = ""
        if pattern.startswith("{time}/{phi}_{theta}_"):
            return "ascent", "info.json has Ascent's name pattern"
    return None, ""


def _angles(table: CinemaTable, convention: Convention) -> tuple[str, str]:
    phi, theta = table.find(*PHI_NAMES), table.find(*THETA_NAMES)
    if phi is None or theta is None:
        lacking = [n for n, c in (("phi (or azimuth)", phi), ("theta (or elevation)", theta)) if c is None]
        raise DatasetError(f"{table.path}: the {convention} convention needs angle columns; the table lacks "
                           f"{' and '.join(lacking)} (columns: {list(table.columns)})")
    return phi, theta


def _angle_cameras(table: CinemaTable, convention: Convention, camera: CinemaCamera) -> np.ndarray:
    phi_col, theta_col = _angles(table, convention)
    phi, theta = table.numbers(phi_col), table.numbers(theta_col)
    what = str(table.path)
    if convention == "paraview":
        focal, distance = paraview_focal_distance(camera, what)
        return np.stack([paraview_c2w(p, t, focal, distance) for p, t in zip(phi, theta, strict=True)])
    centre, distance = ascent_centre_distance(camera, what)
    return np.stack([ascent_c2w(p, t, centre, distance) for p, t in zip(phi, theta, strict=True)])


def _h5_cameras(paths: list[Path], labels: list[str]) -> tuple[np.ndarray, tuple[str, float]]:
    poses, lenses = [], []
    for path, label in zip(paths, labels, strict=True):
        c2w, lens = _h5_camera(_h5_meta(path, label), label)
        poses.append(c2w)
        lenses.append(lens)
    kind, value = lenses[0]
    for i, (k, v) in enumerate(lenses):
        if k != kind or abs(v - value) > LENS_TOLERANCE * max(1.0, abs(value)):
            raise DatasetError(f"{labels[i]}: its camera ({k} {v:g}) differs from {labels[0]}'s ({kind} {value:g}); "
                               "every image of a database must share one lens")
    return np.stack(poses), lenses[0]


def _h5_intrinsics(lens: tuple[str, float], width: int, height: int) -> Intrinsics:
    kind, value = lens
    if kind == "view_height":
        return Intrinsics.from_view_height(width, height, value)
    focal = 0.5 * height / math.tan(math.radians(0.5 * value))  # VTK's view angle is vertical
    return Intrinsics(width, height, focal, focal, 0.5 * width, 0.5 * height)


def _parameters(table: CinemaTable, skip: set[str]) -> tuple[list[str], np.ndarray, list[str]]:
    names, columns, notes = [], [], []
    for name, kind in zip(table.columns, table.types, strict=True):
        if name in skip:
            continue
        if kind == "string":
            notes.append(f"column {name!r}: text, not a parameter")
            continue
        names.append(name)
        columns.append(table.numbers(name))
    values = np.stack(columns, axis=1) if columns else np.zeros((table.n_rows, 0))
    return names, values, notes


def _convention(table: CinemaTable, folder: Path, paths: list[Path], labels: list[str],
                options: CinemaCamera) -> tuple[Convention, str]:
    """The camera convention (named, else detected) and how it was known; DatasetError when neither
    says, or when the images' kind does not fit it."""
    detected, why = _detect(table, folder, paths)
    convention = options.convention or detected
    if convention is None:
        raise DatasetError(f"{table.path}: the database does not say how its cameras were placed; name the "
                           "convention (pycinema, paraview or ascent) as 'convention' in "
                           f"{CAMERA_FILE} or as an option")
    h5 = [p.suffix.lower() == ".h5" for p in paths]
    if convention == "pycinema" and not all(h5):
        raise DatasetError(f"{labels[h5.index(False)]}: the pycinema convention reads cameras from .h5 images")
    if convention != "pycinema" and any(h5):
        raise DatasetError(f"{labels[h5.index(True)]}: .h5 images carry their own cameras: use the pycinema convention")
    return convention, f"named ({convention})" if options.convention else f"{convention}, detected: {why}"


def _cameras(table: CinemaTable, convention: Convention, options: CinemaCamera, paths: list[Path], labels: list[str],
             skip: set[str], notes: list[str]) -> tuple[np.ndarray, tuple[str, float] | None]:
    """Camera-to-world matrices [n, 4, 4] and the images' own lens (pycinema), else None; the angle
    columns join ``skip`` and what they are goes into ``notes``."""
    if convention == "pycinema":
        c2w, lens = _h5_cameras(paths, labels)
        for name in (table.find(*PHI_NAMES), table.find(*THETA_NAMES)):
            if name is not None:
                skip.add(name)
                notes.append(f"column {name!r}: a camera angle (the cameras come from the images)")
        return c2w, lens
    phi, theta = _angles(table, convention)
    skip |= {phi, theta}
    notes.append(f"columns {phi!r}, {theta!r}: the camera's angles")
    return _angle_cameras(table, convention, options), None


def _decode_images(paths: list[Path], labels: list[str], background: np.ndarray,
                   max_workers: int) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Images [n, h, w, 3] composited on ``background``, and the depths [n, h, w] when every image
    (pycinema ``.h5``) has a depth channel."""
    depths: dict[Path, np.ndarray | None] = {}

    def decode(p: Path, bg: np.ndarray, label: str) -> np.ndarray:
        if p.suffix.lower() != ".h5":
            return load_rgb(p, bg, label)
        try:
            rgb, depth = _h5_pixels(p, bg, label)
        except DECODE_ERRORS as exc:
            raise DatasetError(f"{label}: cannot decode {p}: {exc}") from None
        depths[p] = depth
        return rgb

    images = load_images(paths, labels, background, max_workers, decode)
    has_depth = bool(depths) and all(depths[p] is not None for p in paths)
    return images, torch.from_numpy(np.stack([depths[p] for p in paths])) if has_depth else None  # type: ignore[misc]


def read_cinema(path: str | Path, camera: CinemaCamera | None = None, max_workers: int = 2) -> ParsedSplit:
    """Read a Cinema database: every row a frame. ``camera`` overrides the database's ``visnerf_camera.json``."""
    folder = database_folder(path)
    table = read_table(folder / TABLE_FILE)
    options = (camera or CinemaCamera()).over(read_camera_file(folder))
    image_column = _image_column(table)
    paths = _image_paths(table, image_column, folder)
    labels = [f"{table.path}: row {i + 1} ({table.strings(image_column)[i]})" for i in range(table.n_rows)]
    convention, how = _convention(table, folder, paths, labels, options)
    notes = [f"cameras: {how}", f"column {image_column!r}: the images"]
    skip = set(table.file_columns())
    c2w, lens = _cameras(table, convention, options, paths, labels, skip, notes)
    check_rigid(c2w, labels)
    names, values, text_notes = _parameters(table, skip)
    notes += text_notes
    background = np.asarray(options.background, dtype=np.float32)
    if lens is None:
        options.intrinsics(8, 8, str(table.path))  # the lens is known before any image is decoded
    images, depths = _decode_images(paths, labels, background, max_workers)
    height, width = images.shape[1:3]
    intrinsics = _h5_intrinsics(lens, width, height) if lens else options.intrinsics(width, height, str(table.path))
    keep, axes = axes_from_values(names, values)
    notes += [f"column {n!r}: a parameter axis" for j, n in enumerate(names) if j in keep]
    notes += [f"column {n!r}: constant, dropped" for j, n in enumerate(names) if j not in keep]
    scene = SceneData(
        images=images,
        c2w=torch.from_numpy(c2w).float(),
        intrinsics=intrinsics,
        params=torch.from_numpy(values[:, keep]).float() if keep else torch.zeros(table.n_rows, 0),
        param_axes=axes,
        view_ids=torch.from_numpy(view_ids_from_poses(c2w)),
        background=tuple(float(x) for x in background),  # type: ignore[arg-type]
        bbox=None if options.bounds is None else torch.tensor(options.bounds, dtype=torch.float32),
        title=folder.name.removesuffix(".cdb"),
        kind=options.kind,
        file_paths=tuple(str(p) for p in paths),
        source=str(table.path),
        depths=depths,
    )
    return ParsedSplit(scene, tuple(names), values, tuple(notes))
