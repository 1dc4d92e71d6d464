"""Sub-commands ``train``, ``render``, ``calibrate`` and ``info``."""

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from visnerf.checkpoint import CheckpointError, read_checkpoint
from visnerf.config import FACTOR_STORAGE_DTYPES, FieldConfig, HoldoutConfig, RenderConfig, TrainConfig
from visnerf.config_options import add_config_options, given_options
from visnerf.data.cameras import orbit_c2w
from visnerf.runtime import pick_device

if TYPE_CHECKING:
    from visnerf.data.scene import SceneData


def parse_settings(text: str) -> tuple[tuple[float, ...], ...]:
    """``"0.12,0.0225,0.7;0.155,0.0215,0.55"`` -> settings."""
    if not text:
        return ()
    try:
        return tuple(tuple(float(v) for v in part.split(",")) for part in text.split(";") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"cannot read parameter settings {text!r}: use 'a,b,c;d,e,f'") from None


def parse_views(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"cannot read view indices {text!r}: use '0,7,21'") from None


def _number(text: str) -> float:
    """``text`` as a float, NaN when it is not a number (the callers' range checks reject NaN)."""
    try:
        return float(text)
    except ValueError:
        return float("nan")


def positive_float(text: str) -> float:
    """A finite number above zero."""
    value = _number(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a finite number above 0, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """A finite number of at least zero."""
    value = _number(text)
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"expected a finite number of at least 0, got {text!r}")
    return value


def unit_fraction(text: str) -> float:
    """A number in [0, 1]."""
    value = _number(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a fraction in [0, 1], got {text!r}")
    return value


def unit_interval_open_below(text: str) -> float:
    """A number in (0, 1]."""
    value = _number(text)
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a fraction in (0, 1], got {text!r}")
    return value


def _whole_number(text: str, least: int, words: str) -> int:
    """``text`` as a whole number of at least ``least``; ``words`` names the range in the error."""
    try:
        value = int(text)
    except ValueError:
        value = least - 1
    if value < least:
        raise argparse.ArgumentTypeError(f"expected a whole number {words}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """A whole number, 1 or more."""
    return _whole_number(text, 1, "above 0")


def non_negative_int(text: str) -> int:
    """A whole number, 0 or more."""
    return _whole_number(text, 0, ">= 0")


def parse_fractions(text: str) -> tuple[float, ...]:
    """``"0.25,0.5,0.75"`` -> increasing fractions in [0, 1]; ``""`` -> none."""
    values = tuple(unit_fraction(x) for x in text.split(",") if x.strip())
    if any(b <= a for a, b in zip(values, values[1:], strict=False)):
        raise argparse.ArgumentTypeError(f"fractions must increase, got {text!r}")
    return values


def parse_bbox(text: str) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """``"-0.2,-0.2,-0.2,0.2,0.2,0.2"`` -> ((x0, y0, z0), (x1, y1, z1)), finite with x1 > x0 etc."""
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 6 or not all(math.isfinite(x) for x in v):
        raise argparse.ArgumentTypeError(f"cannot read box {text!r}: use six numbers 'X0,Y0,Z0,X1,Y1,Z1'")
    lo, hi = (v[0], v[1], v[2]), (v[3], v[4], v[5])
    if not all(b > a for a, b in zip(lo, hi, strict=True)):
        raise argparse.ArgumentTypeError(f"box {text!r} is empty: each of X1,Y1,Z1 must exceed X0,Y0,Z0")
    return lo, hi


def with_bbox(scene: "SceneData", box: tuple[tuple[float, ...], tuple[float, ...]] | None) -> "SceneData":
    """``scene`` with its content box replaced by ``box`` (unchanged when None)."""
    if box is None:
        return scene
    return dataclasses.replace(scene, bbox=torch.tensor(box, dtype=torch.float32))


def _train(args: argparse.Namespace) -> int:
    from visnerf.data.holdout import split_holdout
    from visnerf.data.parsers.blender import DatasetError, load_dataset
    from visnerf.training.trainer import Trainer

    out = Path(args.out)
    if out.suffix != ".safetensors":
        print(f"error: --out must end in .safetensors, got {out}", file=sys.stderr)
        return 2
    if out.exists() and not args.force and not args.resume:
        print(f"error: {out} exists; pass --force to overwrite it", file=sys.stderr)
        return 2
    device = pick_device(args.device)
    try:
        scene = load_dataset(args.data, "train")
        scene = with_bbox(scene, args.bbox)
        train, val = split_holdout(scene, HoldoutConfig(views=args.holdout_views, settings=args.holdout_params))
    except (DatasetError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if val is None and (Path(args.data) / "transforms_val.json").exists():
        val = load_dataset(args.data, "val")
    cfg = TrainConfig(
        iterations=args.iterations, time_budget_s=args.time_budget * 60 if args.time_budget else None,
        batch_rays=args.batch_rays, micro_batch_rays=args.micro_batch_rays,
        micro_batch_samples=args.micro_batch_samples, seed=args.seed,
        resolution_final=TrainConfig.resolution_final if args.resolution is None else args.resolution,
        validate_every_s=args.validate_every,
        carve_min_seen_fraction=(TrainConfig.carve_min_seen_fraction if args.carve_min_seen_fraction is None
                                 else args.carve_min_seen_fraction),
        occupancy_refine_at=args.occupancy_refine_at, density_grad_keep=args.density_grad_keep,
        occupancy_refine_dilation=args.occupancy_refine_dilation, tv_weight_appearance=args.tv_appearance,
        lr_factors=args.lr_factors, lr_networks=args.lr_networks, lr_decay_ratio=args.lr_decay_ratio,
        weight_average_span=args.weight_average_span, weight_average_from=args.weight_average_from,
    )
    field_cfg = FieldConfig() if args.factor_storage is None else FieldConfig(factor_storage=args.factor_storage)
    render_cfg = RenderConfig()
    init_field, start, carved, choices = None, None, None, []
    if args.resume:
        from visnerf.checkpoint import load_checkpoint
        from visnerf.training.trainer import TrainState

        try:
            init_field, meta = load_checkpoint(args.resume, device)
        except CheckpointError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        prov = meta.provenance
        render_cfg = meta.render  # the resumed model's sample spacing, unless --step-ratio says otherwise
        start = TrainState(iteration=int(prov.get("iterations", 0)), train_seconds=float(prov.get("train_seconds", 0.0)),
                           upsamples_done=int(prov.get("upsamples_done", 0)),
                           occupancy_done=int(prov.get("occupancy_done", 0)),
                           refines_done=int(prov.get("refines_done", 0)))
        if args.factor_storage is not None:
            init_field.cfg = dataclasses.replace(init_field.cfg, factor_storage=args.factor_storage)
    print(f"training on {train.n_frames} frames ({val.n_frames if val else 0} held out), "
          f"K={train.n_params}, {train.intrinsics.width}x{train.intrinsics.height}, device {device}", file=sys.stderr)
    if args.step_ratio is not None:
        render_cfg = dataclasses.replace(render_cfg, step_ratio=args.step_ratio)
    field_given = given_options(args, FieldConfig)
    if init_field is not None and field_given:
        print(f"error: {', '.join('--' + k.replace('_', '-') for k in field_given)} would change the field of "
              f"{args.resume}; a resumed run keeps it", file=sys.stderr)
        return 2
    try:  # the configurations' own checks judge the generated options
        cfg = dataclasses.replace(cfg, **given_options(args, TrainConfig))
        field_cfg = dataclasses.replace(field_cfg, **field_given)
        render_cfg = dataclasses.replace(render_cfg, **given_options(args, RenderConfig))
    except (ValueError, TypeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    setup_seconds = 0.0
    if init_field is None:
        from visnerf.training.recipe import choose_recipe

        t0 = time.perf_counter()
        fixed = {name for name, given in (("resolution_final", args.resolution),
                                          ("carve_min_seen_fraction", args.carve_min_seen_fraction)) if given is not None}
        if {"density_scale", "density_shift"} & set(field_given):
            fixed.add("density_scale")
        recipe = choose_recipe(train, cfg, field_cfg, frozenset(fixed))
        cfg, field_cfg, carved, choices = recipe.train, recipe.field, recipe.carved, recipe.describe()
        setup_seconds = time.perf_counter() - t0
        for choice in choices:
            print(f"  {choice['name']} = {choice['value']}: {choice['reason']}", file=sys.stderr)
    trainer = Trainer(train, val, cfg, device, field_cfg=field_cfg, render_cfg=render_cfg, init_field=init_field,
                      start=start, carved=carved, setup_seconds=setup_seconds)
    trainer.recipe_choices = choices

    def report(row: dict) -> None:
        print("  " + json.dumps(row), file=sys.stderr)

    trainer.run(progress_bar=not args.quiet, on_validate=report)
    path = trainer.save(out, dataset=str(args.data))
    print(f"saved {path} ({path.stat().st_size / 1e6:.2f} MB) and its log {path.with_suffix('.log.csv')}")
    if args.submit:
        from visnerf.upload import UploadError, upload_checkpoint

        try:
            done = upload_checkpoint(path, args.submit, path.name.removesuffix(".safetensors"), None)
        except UploadError as exc:
            print(f"error: {exc} (the checkpoint is saved at {path})", file=sys.stderr)
            return 1
        print(f"{'created' if done.created else 'replaced'} scene {done.scene_id!r} at {done.url}")
    return 0


def _render(args: argparse.Namespace) -> int:
    from PIL import Image

    from visnerf.inference import load_scene

    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        print(f"error: --size must be WxH, got {args.size!r}", file=sys.stderr)
        return 2
    params = {}
    for item in args.param:
        name, _, value = item.partition("=")
        try:
            params[name] = float(value)
        except ValueError:
            print(f"error: --param {item!r} must be NAME=NUMBER", file=sys.stderr)
            return 2
    try:
        scene = load_scene(args.checkpoint, pick_device(args.device))
        cam = scene.info.camera
        distance = args.distance if args.distance is not None else cam.get("distance", 2.0)
        fov = args.fov if args.fov is not None else cam.get("fov_deg", 30.0)
        t0 = time.perf_counter()
        image = scene.render(orbit_c2w(args.azimuth, args.elevation, distance), fov, width, height, params,
                             args.quality)
        ms = 1000 * (time.perf_counter() - t0)
    except (CheckpointError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    Image.fromarray(image).save(args.output)
    print(f"wrote {args.output} ({width}x{height}, {ms:.0f} ms)")
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
    from visnerf.data.holdout import split_holdout
    from visnerf.data.parsers.blender import DatasetError, load_dataset
    from visnerf.evaluation.spacing import choose_full_spacing

    device = pick_device(args.device)
    try:
        field, meta = load_checkpoint(args.checkpoint, device)
        if args.holdout_views or args.holdout_params:
            scene = load_dataset(args.data, "train")
            _, frames = split_holdout(scene, HoldoutConfig(views=args.holdout_views, settings=args.holdout_params))
            if frames is None:
                raise ValueError("the hold-out matches no frame of transforms_train.json")
        elif (Path(args.data) / "transforms_val.json").is_file():
            frames = load_dataset(args.data, "val")
        else:
            raise ValueError(f"{args.data} has no transforms_val.json: name the frames the checkpoint was not "
                             "trained on with --holdout-views / --holdout-params")
        frames = frames_in_checkpoint_axes(frames, meta.param_axes)
        choice = choose_full_spacing(field, frames, meta.render, args.frames, args.tolerance)
    except (CheckpointError, DatasetError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(choice.describe())
    if args.dry_run:
        return 0
    render = dataclasses.replace(meta.render, full_step_ratio=choice.ratio)
    prov = dict(meta.provenance, full_spacing=choice.describe())
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
    doc["tensors"] = {"count": len(tensors), "values": n, "file_mb": round(Path(args.checkpoint).stat().st_size / 1e6, 3)}
    print(json.dumps(doc, indent=2))
    return 0


def add_learning_rate_args(p: argparse.ArgumentParser, networks_default: float = TrainConfig.lr_networks) -> None:
    """``--lr-factors``, ``--lr-networks`` and ``--lr-decay-ratio``, for ``TrainConfig.lr_factors``,
    ``lr_networks`` and ``lr_decay_ratio`` (``visnerf train`` and bench/nyx_train.py)."""
    p.add_argument("--lr-factors", type=positive_float, default=TrainConfig.lr_factors, metavar="LR",
                   help="Adam learning rate of the VM factors and parameter vectors at the start "
                        f"(default {TrainConfig.lr_factors:g}, the paper's; the decoders keep {networks_default:g})")
    paper = ", the paper's" if networks_default == TrainConfig.lr_networks else f"; the paper's {TrainConfig.lr_networks:g}"
    p.add_argument("--lr-networks", type=positive_float, default=networks_default, metavar="LR",
                   help=f"Adam learning rate of the decoders at the start (default {networks_default:g}{paper})")
    p.add_argument("--lr-decay-ratio", type=unit_interval_open_below, default=TrainConfig.lr_decay_ratio,
                   metavar="F", help="fraction of the starting learning rates left at the end of the run, "
                                     f"reached by exponential decay (default {TrainConfig.lr_decay_ratio:g}; "
                                     "1: constant rates)")


def add_weight_average_args(p: argparse.ArgumentParser, span_default: float = TrainConfig.weight_average_span) -> None:
    """``--weight-average-span`` and ``--weight-average-from``, for ``TrainConfig.weight_average_span``
    and ``weight_average_from`` (``visnerf train`` and bench/nyx_train.py)."""
    p.add_argument("--weight-average-span", type=non_negative_float, default=span_default,
                   metavar="F", help="save the parameters' moving average over the end of the run instead of "
                                     "their last values; the fraction of the run over which an old value's weight "
                                     f"falls by e (default {span_default:g}; 0: off)")
    p.add_argument("--weight-average-from", type=unit_fraction, default=TrainConfig.weight_average_from, metavar="F",
                   help="with --weight-average-span, the fraction of the run from which the average is kept "
                        f"(default {TrainConfig.weight_average_from:g})")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train a ViSNeRF model on a dataset folder")
    p.add_argument("data", help="dataset folder with transforms_train.json")
    p.add_argument("--out", required=True, help="checkpoint to write (.safetensors)")
    p.add_argument("--iterations", type=positive_int, default=30000, help="maximum iterations (default 30000)")
    p.add_argument("--time-budget", type=positive_float, default=None, metavar="MINUTES", help="wall-clock training budget")
    p.add_argument("--batch-rays", type=positive_int, default=TrainConfig.batch_rays,
                   help=f"rays per step (default {TrainConfig.batch_rays}; the paper's 4096)")
    p.add_argument("--micro-batch-rays", type=positive_int, default=TrainConfig.micro_batch_rays,
                   help="most rays rendered and back-propagated together; the step is the same for any value, "
                        f"fewer micro-batches are faster and need more memory (default {TrainConfig.micro_batch_rays})")
    p.add_argument("--micro-batch-samples", type=positive_int, default=TrainConfig.micro_batch_samples,
                   help="most samples evaluated (in occupied cells) per micro-batch, which bounds activation "
                        f"memory (default {TrainConfig.micro_batch_samples})")
    p.add_argument("--resolution", type=positive_int, default=None,
                   help="final voxels per axis (cube root of the grid size; default: chosen from the pixel size "
                        "at the content, see `visnerf info`)")
    p.add_argument("--step-ratio", type=positive_float, default=None, metavar="VOXELS",
                   help=f"training sample spacing in voxels (default {RenderConfig.step_ratio:g}; "
                        "with --resume, the checkpoint's)")
    p.add_argument("--carve-min-seen-fraction", type=unit_fraction, default=None,
                   metavar="F", help="fraction of a setting's views that must have a cell in frame for the image "
                                     "carving to keep it (default: 0.75 where every image shows its content whole, "
                                     "else 0)")
    p.add_argument("--occupancy-refine-at", type=parse_fractions, default=TrainConfig.occupancy_refine_at,
                   metavar="P1,P2,..", help="fractions of the run at which the occupancy grid is rebuilt "
                                            "within itself, so later steps sample fewer empty cells (default "
                                            f"{','.join(f'{x:g}' for x in TrainConfig.occupancy_refine_at)})")
    p.add_argument("--occupancy-refine-dilation", type=non_negative_int,
                   default=TrainConfig.occupancy_refine_dilation, metavar="CELLS",
                   help="cells by which a refined occupancy grid grows around the cells with content "
                        f"(default {TrainConfig.occupancy_refine_dilation})")
    p.add_argument("--density-grad-keep", type=unit_interval_open_below, default=TrainConfig.density_grad_keep,
                   metavar="F", help="fraction of the near-empty density samples (alpha below "
                                     f"{TrainConfig.density_grad_floor:g}) each step back-propagates, their gradient "
                                     f"scaled by 1/F: an unbiased, cheaper step (default {TrainConfig.density_grad_keep:g}; 1: all)")
    p.add_argument("--tv-appearance", type=non_negative_float, default=TrainConfig.tv_weight_appearance,
                   metavar="W", help="total-variation weight of the appearance factors "
                                     f"(default {TrainConfig.tv_weight_appearance:g})")
    add_learning_rate_args(p)
    add_weight_average_args(p)
    p.add_argument("--factor-storage", choices=sorted(FACTOR_STORAGE_DTYPES), default=None,
                   help=f"how the checkpoint stores the VM factors (default {FieldConfig.factor_storage}; "
                        "with --resume, the checkpoint's); int8: planes as int8 codes with row scales, about "
                        "half the float16 file")
    p.add_argument("--holdout-views", type=parse_views, default=(), metavar="I,J,..",
                   help="view indices held out for validation at every parameter setting")
    p.add_argument("--holdout-params", type=parse_settings, default=(), metavar="A,B;C,D",
                   help="parameter settings held out for validation (all their views)")
    p.add_argument("--bbox", type=parse_bbox, default=None, metavar="X0,Y0,Z0,X1,Y1,Z1",
                   help="world box that holds the content (write --bbox=-1,... for negative numbers); "
                        "default: the dataset's bbox, else a box every camera sees, carved from the images")
    p.add_argument("--validate-every", type=positive_float, default=TrainConfig.validate_every_s, metavar="SECONDS",
                   help=f"training seconds between validations on the held-out frames (default {TrainConfig.validate_every_s:g})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    p.add_argument("--resume", default=None, metavar="CKPT", help="continue from this checkpoint's weights")
    p.add_argument("--submit", default=None, metavar="URL", help="upload the checkpoint to a server when done")
    p.add_argument("--force", action="store_true", help="overwrite --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_config_options(p)
    p.set_defaults(func=_train)

    r = sub.add_parser("render", help="render one frame from a checkpoint")
    r.add_argument("checkpoint")
    r.add_argument("--azimuth", type=float, default=0.0)
    r.add_argument("--elevation", type=float, default=0.0)
    r.add_argument("--distance", type=float, default=None)
    r.add_argument("--fov", type=float, default=None, help="horizontal field of view in degrees")
    r.add_argument("--param", action="append", default=[], metavar="NAME=VALUE")
    r.add_argument("--size", default="256x256", metavar="WxH")
    r.add_argument("--quality", choices=("full", "preview"), default="full")
    r.add_argument("--device", default="auto")
    r.add_argument("-o", "--output", required=True)
    r.set_defaults(func=_render)

    c = sub.add_parser("calibrate", help="choose a checkpoint's full-quality sample spacing on held-out frames")
    c.add_argument("checkpoint", help="checkpoint to measure and update in place (written atomically)")
    c.add_argument("data", help="dataset folder: transforms_val.json, or the training split with --holdout-*")
    c.add_argument("--holdout-views", type=parse_views, default=(), metavar="I,J,..",
                   help="the views held out in training (frames of transforms_train.json)")
    c.add_argument("--holdout-params", type=parse_settings, default=(), metavar="A,B;C,D",
                   help="the parameter settings held out in training")
    c.add_argument("--frames", type=int, default=16, help="frames to measure on (evenly chosen, default 16)")
    c.add_argument("--tolerance", type=float, default=0.05, metavar="DB",
                   help="PSNR the full-quality frames may lose against exhaustive ones (default 0.05)")
    c.add_argument("--dry-run", action="store_true", help="measure and print, leave the checkpoint alone")
    c.add_argument("--device", default="auto")
    c.set_defaults(func=_calibrate)

    i = sub.add_parser("info", help="print a checkpoint's metadata")
    i.add_argument("checkpoint")
    i.set_defaults(func=_info)


__all__ = ["register"]
