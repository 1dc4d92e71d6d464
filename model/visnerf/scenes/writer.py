"""Write a synthetic scene as a dataset in the project's data format (NeRF-Blender convention).

Layout: ``DIR/train/r_N.png``, ``DIR/test/r_N.png`` (8-bit RGB on a white background, or RGBA with
straight alpha for a scene that says ``rgba``) and
``DIR/transforms_{train,test}.json``. The images come first, then the test JSON, and the training
JSON last, each JSON written to a temporary name and renamed: an interrupted run never leaves a
complete-looking dataset behind.
"""

import json
import multiprocessing
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from jaxtyping import UInt8
from PIL import Image
from tqdm import tqdm

import visnerf
from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.scenes.catalog import SceneSpec, scene_catalog
from visnerf.scenes.protocol import (
    direction_to_angles,
    parameter_settings,
    path_angles,
    path_params,
    training_directions,
)
from visnerf.scenes.reference_renderer import MarchConfig, RayOutput
from visnerf.scenes.shells_kernel import render_image_fast


@dataclass(frozen=True)
class DatasetOptions:
    """Size of the generated dataset."""

    resolution: int = 128
    """Width and height of every image in pixels (>= 8)."""
    n_views: int = 42
    """Training views per parameter setting (42: the level-1 icosphere)."""
    n_test_views: int = 181
    """Views on the test path."""


@dataclass(frozen=True)
class Frame:
    """One image to render."""

    split: Literal["train", "test"]
    """Which transforms file lists it."""
    index: int
    """N in ``r_N.png`` within its split."""
    params: tuple[float, ...]
    """Values of the scene's varying parameters."""
    azimuth: float
    """Orbit azimuth in degrees."""
    elevation: float
    """Orbit elevation in degrees."""


@dataclass(frozen=True)
class WriteSummary:
    """What ``write_scene`` produced."""

    n_train: int
    """Training images written."""
    n_test: int
    """Test images written."""
    seconds: float
    """Wall-clock time of the whole generation."""


def plan_frames(spec: SceneSpec, options: DatasetOptions) -> list[Frame]:
    """Every frame of the dataset: training views (view-major, like the Nyx data), then the test path."""
    settings = parameter_settings(spec.axes)
    frames = []
    for direction in training_directions(options.n_views):
        azimuth, elevation = direction_to_angles(direction)
        for setting in settings:
            frames.append(Frame("train", len(frames), setting, azimuth, elevation))
    angles = path_angles(options.n_test_views)
    params = path_params(spec.axes, options.n_test_views)
    for i, ((azimuth, elevation), setting) in enumerate(zip(angles, params, strict=True)):
        frames.append(Frame("test", i, setting, azimuth, elevation))
    return frames


def render_frame(spec: SceneSpec, frame: Frame, resolution: int) -> UInt8[np.ndarray, "h w c"]:
    """The 8-bit RGB image of one frame (RGBA, ``c = 4``, for a scene that says ``rgba``)."""
    c2w = torch.tensor(orbit_c2w(frame.azimuth, frame.elevation, spec.camera_distance), dtype=torch.float32)
    intrinsics = Intrinsics.from_fov(resolution, resolution, spec.fov_x_rad)
    config = MarchConfig(step=spec.step)
    output = render_image_fast(spec.volume_at(frame.params), c2w, intrinsics, config)
    image = straight_rgba(output, config.background) if spec.rgba else output.rgb.clamp(0.0, 1.0)
    return (image.reshape(resolution, resolution, -1) * 255.0).round().to(torch.uint8).numpy()


def straight_rgba(output: RayOutput, background: tuple[float, float, float]) -> torch.Tensor:
    """``[n, 4]`` colour and opacity with straight (not premultiplied) alpha: the colour that,
    composited over ``background`` with the ray's opacity, gives the rendered colour (0 where the
    ray is clear). Guarded: the division only where the opacity is above float32's tiny."""
    alpha = output.opacity.clamp(0.0, 1.0)[:, None]  # [n, 1]
    back = torch.tensor(background, dtype=output.rgb.dtype, device=output.rgb.device)
    seen = alpha > torch.finfo(torch.float32).tiny
    colour = (output.rgb - (1.0 - alpha) * back) / torch.where(seen, alpha, torch.ones_like(alpha))
    return torch.cat([torch.where(seen, colour, torch.zeros_like(colour)).clamp(0.0, 1.0), alpha], dim=-1)


def output_dir_problem(out_dir: Path, force: bool) -> str | None:
    """Why ``out_dir`` cannot receive a dataset, or None when it can."""
    if out_dir.exists() and not out_dir.is_dir():
        return f"output path {out_dir} exists and is not a directory"
    if out_dir.is_dir() and any(out_dir.iterdir()) and not force:
        return f"output directory {out_dir} is not empty (use --force to overwrite)"
    return None


def _clear_previous(out_dir: Path) -> None:
    for split in ("train", "val", "test"):
        (out_dir / f"transforms_{split}.json").unlink(missing_ok=True)
    for split in ("train", "test"):
        for old in (out_dir / split).glob("r_*.png") if (out_dir / split).is_dir() else ():
            old.unlink()


def _frame_entry(spec: SceneSpec, frame: Frame) -> dict:
    c2w = orbit_c2w(frame.azimuth, frame.elevation, spec.camera_distance)
    return {
        "file_path": f"./{frame.split}/r_{frame.index}",
        "transform_matrix": c2w.tolist(),
        "params": list(frame.params),
        "view": {"azimuth": frame.azimuth, "elevation": frame.elevation, "distance": spec.camera_distance},
    }


def transforms_document(spec: SceneSpec, options: DatasetOptions, frames: list[Frame]) -> dict:
    """The JSON document of one split (``frames`` all from that split)."""
    document = {
        "camera_angle_x": spec.fov_x_rad,
        "param_names": spec.param_names,
        "white_background": True,
        "bbox": [list(spec.bbox[0]), list(spec.bbox[1])],
        "scene": {
            "name": spec.name,
            "title": spec.title,
            "kind": spec.kind,
            "description": spec.description,
            "fixed": dict(spec.fixed),
        },
        "generator": {
            "tool": "visnerf make-scene",
            "version": visnerf.__version__,
            "renderer": "visnerf.scenes.reference_renderer",
            "step": spec.step,
            "resolution": [options.resolution, options.resolution],
            "views_per_setting": options.n_views,
        },
        "frames": [_frame_entry(spec, frame) for frame in frames],
    }
    if frames and frames[0].split == "test":
        document["test_path"] = (
            "azimuth -180 -> 180 and elevation -90 -> 90 linearly; parameters sweep their ranges "
            "(with several: first half one at a time, second half together), always between "
            "training values (at least a quarter of a spacing away)"
        )
    return document


def _write_json_atomically(path: Path, document: dict) -> None:
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(json.dumps(document, indent=1))
    os.replace(temporary, path)


def _save_frames(spec: SceneSpec, frames: list[Frame], resolution: int, out_dir: Path) -> int:
    for frame in frames:
        image = render_frame(spec, frame, resolution)
        Image.fromarray(image).save(out_dir / frame.split / f"r_{frame.index}.png")
    return len(frames)


def _save_frames_in_worker(job: tuple[str, list[Frame], int, str]) -> int:
    name, frames, resolution, out_dir = job
    torch.set_num_threads(1)
    return _save_frames(scene_catalog()[name], frames, resolution, Path(out_dir))


def write_scene(
    spec: SceneSpec, out_dir: Path, options: DatasetOptions, progress: bool = True, workers: int = 1
) -> WriteSummary:
    """Render and write the whole dataset; replaces a previous dataset in ``out_dir``.

    ``workers > 1`` renders in that many processes (one torch thread each); it needs a scene of
    ``scene_catalog()``, which the workers look up by name.
    """
    if options.resolution < 8:
        raise ValueError(f"resolution must be at least 8 pixels, got {options.resolution}")
    if workers > 1 and scene_catalog().get(spec.name) != spec:
        raise ValueError(f"workers > 1 needs a scene from the catalog, not {spec.name!r}")
    started = time.perf_counter()
    frames = plan_frames(spec, options)
    out_dir.mkdir(parents=True, exist_ok=True)
    _clear_previous(out_dir)
    for split in ("train", "test"):
        (out_dir / split).mkdir(exist_ok=True)
    with tqdm(total=len(frames), desc=spec.name, unit="img", disable=not progress, leave=False) as bar:
        if workers <= 1:
            for frame in frames:
                bar.update(_save_frames(spec, [frame], options.resolution, out_dir))
        else:
            jobs = [
                (spec.name, frames[i : i + 8], options.resolution, str(out_dir))
                for i in range(0, len(frames), 8)
            ]
            with multiprocessing.get_context("spawn").Pool(workers) as pool:
                for done in pool.imap_unordered(_save_frames_in_worker, jobs):
                    bar.update(done)
    train = [f for f in frames if f.split == "train"]
    test = [f for f in frames if f.split == "test"]
    _write_json_atomically(out_dir / "transforms_test.json", transforms_document(spec, options, test))
    _write_json_atomically(out_dir / "transforms_train.json", transforms_document(spec, options, train))
    return WriteSummary(len(train), len(test), time.perf_counter() - started)
