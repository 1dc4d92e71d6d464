"""Sub-commands ``train`` (in ``train_command``), ``render``, ``calibrate`` and ``info``."""

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from visnerf.arg_types import add_device_option
from visnerf.checkpoint import CheckpointError, read_checkpoint
from visnerf.cinema_options import add_cinema_options, cinema_camera
from visnerf.config import FramesConfig
from visnerf.config.bake import BakeConfig
from visnerf.config_options import add_config_options, config_from_args, frames_config
from visnerf.data.cameras import orbit_c2w
from visnerf.holdout_options import add_holdout_options, holdout_config
from visnerf.runtime import pick_device
from visnerf.train_command import register_train

if TYPE_CHECKING:
    from visnerf.data.scene import SceneData


def parse_params(items: list[str]) -> dict[str, float] | None:
    """``--param NAME=NUMBER`` options by name; None (the error printed) for one that is not."""
    params = {}
    for item in items:
        name, _, value = item.partition("=")
        try:
            params[name] = float(value)
        except ValueError:
            print(f"error: --param {item!r} must be NAME=NUMBER", file=sys.stderr)
            return None
    return params


def _render(args: argparse.Namespace) -> int:
    from PIL import Image

    from visnerf.inference import load_scene
    from visnerf.lens import choose_lens

    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        print(f"error: --size must be WxH, got {args.size!r}", file=sys.stderr)
        return 2
    params = parse_params(args.param)
    if params is None:
        return 2
    if args.bake and params:
        print("error: a bake holds one setting: give --param to `visnerf bake`, not with --bake", file=sys.stderr)
        return 2
    try:
        scene = load_scene(args.checkpoint, pick_device(args.device), frames_config(args))
        cam = scene.info.camera
        distance = args.distance if args.distance is not None else cam.get("distance", 2.0)
        fov, view_height = choose_lens(cam, args.fov, args.view_height)
        c2w = orbit_c2w(args.azimuth, args.elevation, distance)
        t0 = time.perf_counter()
        if args.bake:
            image = _render_bake(args.bake, c2w, fov, view_height, width, height)
        else:
            image = scene.render(c2w, fov, width, height, params, args.quality, view_height=view_height)
        ms = 1000 * (time.perf_counter() - t0)
    except (CheckpointError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    Image.fromarray(image).save(args.output)
    print(f"wrote {args.output} ({width}x{height}, {ms:.0f} ms)")
    return 0


def _render_bake(path: str, c2w: object, fov: float | None, view_height: float | None, width: int,
                 height: int) -> object:
    import math

    import torch

    from visnerf.bake.bake_file import read_bake
    from visnerf.bake.bake_render import DenseBake, render_bake
    from visnerf.data.cameras import Intrinsics

    intrinsics = (Intrinsics.from_fov(width, height, math.radians(fov)) if fov is not None
                  else Intrinsics.from_view_height(width, height, float(view_height)))  # type: ignore[arg-type]
    return render_bake(DenseBake.of(read_bake(path)), torch.as_tensor(c2w, dtype=torch.float32), intrinsics)


def _bake(args: argparse.Namespace) -> int:
    from visnerf.bake.bake_file import BakeError, write_bake
    from visnerf.bake.baking import content_hash
    from visnerf.bake.scene_bake import bake_scene
    from visnerf.inference import load_scene

    params = parse_params(args.param)
    if params is None:
        return 2
    try:
        scene = load_scene(args.checkpoint, pick_device("cpu"))
        t0 = time.perf_counter()
        bake = bake_scene(scene, params, config_from_args(BakeConfig, args),
                          content_hash(Path(args.checkpoint).read_bytes()))
        seconds = time.perf_counter() - t0
        size = write_bake(bake, args.output)
    except (CheckpointError, BakeError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    h = bake.header
    grid = "x".join(map(str, h.grid))
    print(f"wrote {args.output} ({size / 1e6:.2f} MB, {len(bake.bricks)} bricks of {h.brick}^3, grid {grid}, "
          f"{h.shading} shading, {seconds:.2f} s)")
    print(f"colour: {h.source.get('sh_degree', '')}")
    return 0


def frames_in_checkpoint_axes(scene: "SceneData", axes: tuple) -> "SceneData":
    """``scene`` with its parameter columns reordered to a checkpoint's axes and normalised by
    their ranges (a dataset split's own ranges may differ). Raises ValueError naming an axis the
    frames do not vary, or a value outside the checkpoint's range."""
    columns = {a.name: k for k, a in enumerate(scene.param_axes)}
    missing = [a.name for a in axes if a.name not in columns]
    extra = sorted(set(columns) - {a.name for a in axes})
    if missing or extra:
        raise ValueError(f"the frames' parameters {sorted(columns)} are not the checkpoint's {[a.name for a in axes]}")
    params = scene.params[:, [columns[a.name] for a in axes]] if axes else scene.params[:, :0]
    for k, a in enumerate(axes):
        if not all(a.contains(float(v)) for v in params[:, k]):
            raise ValueError(f"parameter {a.name!r} of the frames leaves the checkpoint's range [{a.min}, {a.max}]")
    return dataclasses.replace(scene, params=params, param_axes=tuple(axes))


def _calibrate(args: argparse.Namespace) -> int:
    from visnerf.checkpoint import load_checkpoint, save_checkpoint
    from visnerf.data.datasets import DatasetError, has_split, load_dataset
    from visnerf.data.holdout import split_holdout
    from visnerf.evaluation.spacing import choose_full_spacing

    device = pick_device(args.device)
    try:
        field, meta = load_checkpoint(args.checkpoint, device)
        on_training_frames = False
        cinema = cinema_camera(args)
        if args.holdout_views or args.holdout_params or args.holdout_value:
            scene = load_dataset(args.data, "train", cinema)
            _, frames = split_holdout(scene, holdout_config(scene, args))
            if frames is None:
                raise ValueError("the hold-out matches no frame of the training split")
        elif has_split(args.data, "val"):
            frames = load_dataset(args.data, "val")
        else:
            # as training does with nothing held out: the choice weighs sampling error against the
            # exhaustive render of the same frame, which training frames show as well
            frames, on_training_frames = load_dataset(args.data, "train", cinema), True
        frames = frames_in_checkpoint_axes(frames, meta.param_axes)
        choice = choose_full_spacing(field, frames, meta.render, args.frames, args.tolerance)
    except (CheckpointError, DatasetError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    note = choice.describe(training_frames=on_training_frames)
    print(note)
    if args.dry_run:
        return 0
    render = dataclasses.replace(meta.render, full_step_ratio=choice.ratio)
    prov = dataclasses.replace(meta.provenance, full_spacing=note)
    save_checkpoint(field, dataclasses.replace(meta, render=render, provenance=prov), args.checkpoint)
    print(f"wrote full_step_ratio {choice.ratio:g} into {args.checkpoint}")
    return 0


def _info(args: argparse.Namespace) -> int:
    try:
        meta, tensors = read_checkpoint(args.checkpoint)
    except CheckpointError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    n = sum(t.numel() for t in tensors.values())
    doc = json.loads(meta.to_json())
    file_mb = round(Path(args.checkpoint).stat().st_size / 1e6, 3)
    doc["tensors"] = {"count": len(tensors), "values": n, "file_mb": file_mb}
    from visnerf.bake.baking import bake_grid

    cfg = BakeConfig()
    doc["bake"] = {
        "grid": list(bake_grid(tuple(meta.field.resolution), cfg)),  # type: ignore[arg-type]
        "grid_rule": "the model's own grid (docs/decisions.md#bake.grid)",
        "colour": f"spherical harmonics of the view of degree up to {cfg.max_sh_degree}, the lowest whose fit is "
                  f"within {cfg.sh_tolerance:g} level of RMS error of the highest, chosen at each bake"
                  + (f", and the level field's normal cosine with its powers {list(meta.field.level_cosine_powers)}"
                     if meta.field.level_set_axis >= 0 else "") + " (docs/decisions.md#bake.shading)",
    }
    print(json.dumps(doc, indent=2))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    register_train(sub)

    r = sub.add_parser("render", help="render one frame from a checkpoint")
    r.add_argument("checkpoint")
    r.add_argument("--azimuth", type=float, default=0.0)
    r.add_argument("--elevation", type=float, default=0.0)
    r.add_argument("--distance", type=float, default=None)
    r.add_argument("--fov", type=float, default=None, help="horizontal field of view in degrees (perspective)")
    r.add_argument("--view-height", type=float, default=None, metavar="UNITS",
                   help="world units the image spans vertically (orthographic; the default for a scene "
                        "trained from orthographic images)")
    r.add_argument("--param", action="append", default=[], metavar="NAME=VALUE")
    r.add_argument("--size", default="256x256", metavar="WxH")
    r.add_argument("--quality", choices=("full", "preview"), default="full")
    add_device_option(r)
    r.add_argument("--bake", metavar="FILE", default=None,
                   help="draw from a bake (`visnerf bake`) instead of the model: the browser's reference renderer")
    r.add_argument("-o", "--output", required=True)
    add_config_options(r, (FramesConfig,))
    r.set_defaults(func=_render)

    b = sub.add_parser("bake", help="bake one parameter setting into a file the browser draws")
    b.add_argument("checkpoint")
    b.add_argument("--param", action="append", default=[], metavar="NAME=VALUE")
    b.add_argument("-o", "--output", required=True)
    add_config_options(b, (BakeConfig,))
    b.set_defaults(func=_bake)

    c = sub.add_parser("calibrate", help="choose a checkpoint's full-quality sample spacing on held-out frames "
                                         "(on training frames when none are held out)")
    c.add_argument("checkpoint", help="checkpoint to measure and update in place (written atomically)")
    c.add_argument("data", help="dataset folder: transforms_val.json, the training split with --holdout-*, else "
                                "the training frames")
    add_holdout_options(c, "in training: give those the run held out")
    c.add_argument("--frames", type=int, default=16, help="frames to measure on (evenly chosen, default 16)")
    c.add_argument("--tolerance", type=float, default=0.05, metavar="DB",
                   help="PSNR the full-quality frames may lose against exhaustive ones (default 0.05)")
    c.add_argument("--dry-run", action="store_true", help="measure and print, leave the checkpoint alone")
    add_device_option(c)
    add_cinema_options(c)
    c.set_defaults(func=_calibrate)

    i = sub.add_parser("info", help="print a checkpoint's metadata")
    i.add_argument("checkpoint")
    i.set_defaults(func=_info)


__all__ = ["register"]
