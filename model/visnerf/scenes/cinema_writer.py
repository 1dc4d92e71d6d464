"""Write a synthetic scene as Cinema databases, in the conventions of the producers our users run.

Layout: ``DIR/train.cdb`` (the training views) and ``DIR/test.cdb`` (the test path), each a
Spec D database (``data.csv``, the images, ``visnerf_camera.json`` with what its angles lack):
- ``pycinema``: orthographic ``.h5`` images (``channels/rgba``, ``channels/depth``, the camera in
  ``meta/``, its up vector deliberately not orthogonal to the view, as producers write it);
- ``paraview``: PNG images in a ``FILE_png`` column written first, ``phi``/``theta`` written
  zero-padded, a ``producer`` column naming ParaView;
- ``ascent``: PNG images under ``{time}/``, header ``phi,theta,time,...,FILE``, an ``info.json``
  with Ascent's name pattern, the cameras 1.25 box diagonals from the box centre.
Every image is rendered by the reference renderer from the camera that the convention's reader
reconstructs, so the readers are tested against ground truth. Each table and sidecar is written
under a temporary name and renamed, the training table last.
"""

import csv
import io
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.data.parsers.cinema_cameras import (
    ASCENT_DISTANCE_PER_DIAGONAL,
    CAMERA_FILE,
    Convention,
    ascent_angles,
    ascent_c2w,
)
from visnerf.scenes.catalog import SceneSpec
from visnerf.scenes.reference_renderer import MarchConfig, RayOutput, render_image
from visnerf.scenes.writer import DatasetOptions, Frame, plan_frames

SPLIT_FOLDERS = {"train": "train.cdb", "test": "test.cdb"}


@dataclass(frozen=True)
class CinemaView:
    """One frame's camera as the convention writes it, and the pose and lens its reader rebuilds."""

    c2w: np.ndarray
    intrinsics: Intrinsics
    phi: float
    theta: float


def _ascent_geometry(spec: SceneSpec) -> tuple[np.ndarray, float]:
    lo, hi = (np.asarray(b, dtype=np.float64) for b in spec.bbox)
    return 0.5 * (lo + hi), ASCENT_DISTANCE_PER_DIAGONAL * float(np.linalg.norm(hi - lo))


def _ascent_fov_deg(spec: SceneSpec) -> float:
    """The field of view that frames the content at Ascent's distance as the scene's own camera does."""
    _, distance = _ascent_geometry(spec)
    half = math.atan(math.tan(0.5 * spec.fov_x_rad) * spec.camera_distance / distance)
    return math.degrees(2.0 * half)


def view_height(spec: SceneSpec) -> float:
    """The orthographic view that spans what the scene's pinhole camera sees at the orbit centre."""
    return 2.0 * spec.camera_distance * math.tan(0.5 * spec.fov_x_rad)


def cinema_view(spec: SceneSpec, frame: Frame, convention: Convention, resolution: int) -> CinemaView:
    """The camera of ``frame`` under ``convention``."""
    orbit = orbit_c2w(frame.azimuth, frame.elevation, spec.camera_distance)
    if convention == "ascent":
        centre, distance = _ascent_geometry(spec)
        phi, theta = ascent_angles(orbit[:3, 2])
        intr = Intrinsics.from_fov(resolution, resolution, math.radians(_ascent_fov_deg(spec)))
        return CinemaView(ascent_c2w(phi, theta, tuple(centre), distance), intr, phi, theta)
    if convention == "pycinema":
        intr = Intrinsics.from_view_height(resolution, resolution, view_height(spec))
        return CinemaView(orbit, intr, frame.azimuth, frame.elevation)
    intrinsics = Intrinsics.from_fov(resolution, resolution, spec.fov_x_rad)
    return CinemaView(orbit, intrinsics, frame.azimuth, frame.elevation)


def _render(spec: SceneSpec, frame: Frame, view: CinemaView) -> RayOutput:
    c2w = torch.tensor(view.c2w, dtype=torch.float32)
    return render_image(spec.volume_at(frame.params), c2w, view.intrinsics, MarchConfig(step=spec.step))


def _rgb8(output: RayOutput, resolution: int) -> np.ndarray:
    rgb = output.rgb.reshape(resolution, resolution, 3).clamp(0.0, 1.0)
    return (rgb * 255.0).round().to(torch.uint8).numpy()


def _rgba8(output: RayOutput, resolution: int) -> np.ndarray:
    """Straight (not premultiplied) colour and coverage: composited on white it gives the RGB frame back."""
    alpha = output.opacity.reshape(resolution, resolution, 1).clamp(0.0, 1.0)
    rgb = output.rgb.reshape(resolution, resolution, 3).clamp(0.0, 1.0)
    straight = torch.where(alpha > 1e-6, (rgb - (1.0 - alpha)) / alpha.clamp_min(1e-6), torch.ones_like(rgb))
    rgba = torch.cat([straight.clamp(0.0, 1.0), alpha], dim=-1)
    return (rgba * 255.0).round().to(torch.uint8).numpy()


def _write_h5(path: Path, output: RayOutput, view: CinemaView, resolution: int, near_far: tuple[float, float]) -> None:
    import h5py

    depth = output.depth.reshape(resolution, resolution).numpy().astype(np.float32)
    depth = np.where(np.isfinite(depth) & (output.opacity.reshape(resolution, resolution).numpy() > 0.5), depth, np.nan)
    back, up = view.c2w[:3, 2], view.c2w[:3, 1]
    with h5py.File(path, "w") as f:
        meta, channels = f.create_group("meta"), f.create_group("channels")
        meta["CameraPos"] = view.c2w[:3, 3]
        meta["CameraDir"] = -back
        meta["CameraUp"] = up - 0.3 * back  # producers write an up vector that is not orthogonal to the view
        meta["CameraNearFar"] = np.asarray(near_far, dtype=np.float64)
        meta["CameraHeight"] = np.asarray([view.intrinsics.view_height])
        meta["Phi"], meta["Theta"] = np.asarray([view.phi]), np.asarray([view.theta])
        meta["resolution"] = np.asarray([resolution, resolution])
        channels["rgba"] = _rgba8(output, resolution)
        channels["depth"] = depth


def _angle(value: float) -> str:
    """ParaView writes angles zero-padded (``060.00``); ten decimals keep poses to 1e-9."""
    return f"{value:017.10f}"


def _write_atomically(path: Path, text: str) -> None:
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(text)
    os.replace(temporary, path)


def _table(spec: SceneSpec, convention: Convention, rows: list[tuple[Frame, CinemaView, str]]) -> str:
    names = list(spec.param_names)
    if convention == "paraview":
        header = ["FILE_png", "phi", "theta", *names, "producer"]
    elif convention == "ascent":
        header = ["phi", "theta", *([] if "time" in names else ["time"]), *names, "FILE"]
    else:
        header = ["phi", "theta", *names, "FILE"]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    for frame, view, file in rows:
        params = [repr(float(v)) for v in frame.params]
        if convention == "paraview":
            writer.writerow([file, _angle(view.phi), _angle(view.theta), *params, "ParaView 5.13"])
        elif convention == "ascent":
            writer.writerow([repr(view.phi), repr(view.theta), *([] if "time" in names else ["0.0"]), *params, file])
        else:
            writer.writerow([repr(view.phi), repr(view.theta), *params, file])
    return buffer.getvalue()


def _sidecar(spec: SceneSpec, convention: Convention) -> dict:
    doc: dict = {"kind": spec.kind, "bounds": [list(spec.bbox[0]), list(spec.bbox[1])]}
    if convention == "paraview":
        doc.update(focal_point=[0.0, 0.0, 0.0], distance=spec.camera_distance, fov_deg=spec.fov_x_deg)
    elif convention == "ascent":
        doc.update(fov_deg=_ascent_fov_deg(spec))
    return doc


def write_cinema_scene(spec: SceneSpec, out_dir: Path, options: DatasetOptions, convention: Convention) -> int:
    """Render and write ``DIR/train.cdb`` and ``DIR/test.cdb``; the number of images written."""
    if options.resolution < 8:
        raise ValueError(f"resolution must be at least 8 pixels, got {options.resolution}")
    frames = plan_frames(spec, options)
    near_far = (max(1e-3, spec.camera_distance - 1.0), spec.camera_distance + 1.0)
    for split in ("test", "train"):
        folder = out_dir / SPLIT_FOLDERS[split]
        (folder / "0.0" if convention == "ascent" else folder).mkdir(parents=True, exist_ok=True)
        rows = []
        for frame in (f for f in frames if f.split == split):
            view = cinema_view(spec, frame, convention, options.resolution)
            output = _render(spec, frame, view)
            if convention == "pycinema":
                file = f"r_{frame.index}.h5"
                _write_h5(folder / file, output, view, options.resolution, near_far)
            else:
                file = f"0.0/r_{frame.index}.png" if convention == "ascent" else f"r_{frame.index}.png"
                Image.fromarray(_rgb8(output, options.resolution)).save(folder / file)
            rows.append((frame, view, file))
        if convention == "ascent":
            info = {"type": "simple", "version": "1.1", "metadata": {"type": "parametric-image-stack"},
                    "name_pattern": "{time}/{phi}_{theta}_" + spec.name + ".png"}
            _write_atomically(folder / "info.json", json.dumps(info, indent=1))
        _write_atomically(folder / CAMERA_FILE, json.dumps(_sidecar(spec, convention), indent=1))
        _write_atomically(folder / "data.csv", _table(spec, convention, rows))
    return len(frames)
