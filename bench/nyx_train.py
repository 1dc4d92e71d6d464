"""Train on shared/data/nyx under a wall-clock budget and record what it reaches.

Held out for validation: four whole parameter settings (interpolation between training settings)
and four views at every other setting. Records validation PSNR/SSIM against training time,
iterations per second, peak RSS, checkpoint size and seconds per 256x256 frame.

    .venv/bin/python bench/nyx_train.py --minutes 60

Writes the checkpoint to runs/nyx.safetensors (``--out``) and nyx_train.json, .md and .png to
bench/results/nyx_train_nyx/ (``--results``; by default named after the checkpoint). It refuses,
before training, to write over a checkpoint or a report that exists (``--force`` does).
"""

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch
from bench_common import (
    HOLDOUT_SETTINGS,
    HOLDOUT_VIEWS,
    ROOT,
    cpu_description,
    evenly_spaced,
    holdout_for,
    render_frame,
    write_json,
)

from visnerf.commands import (
    add_error_sampling_args,
    add_learning_rate_args,
    add_weight_average_args,
    non_negative_float,
    non_negative_int,
    parse_bbox,
    parse_fractions,
    pick_device,
    positive_float,
    positive_int,
    unit_fraction,
    unit_interval_open_below,
    with_bbox,
)
from visnerf.config import FACTOR_STORAGE_DTYPES, FieldConfig, RenderConfig, TrainConfig
from visnerf.data.holdout import split_holdout
from visnerf.data.parsers.blender import load_dataset
from visnerf.evaluation.colour_difference import luv_difference
from visnerf.evaluation.evaluate import EvalConfig
from visnerf.evaluation.metrics import psnr, ssim
from visnerf.evaluation.plots import plot_difference
from visnerf.inference import load_scene
from visnerf.training.trainer import Trainer

# The Nyx recipe, where it differs from the library's defaults (TrainConfig, RenderConfig), and why.
NYX_CARVE_MIN_SEEN_FRACTION = 0.75
"""Every view sees all of Nyx, so a cell that a quarter of a setting's views do not see is not
content: the box carves to +-0.19 instead of +-0.31 on two axes (data/carving.py). The library
keeps 0, which cannot carve content that only a few views see."""
NYX_RESOLUTION = 200
"""Voxels per axis at the end: 0.0019 world units a voxel (a pixel is 0.0021 at the origin), 8.92 MB
with int8 planes. Nyx's detail sits at the pixel scale: its images downsampled 1.5 and 2 times and
upsampled back are 24.48 and 23.92 dB from themselves (bench/results/resolution_ceiling.md). 160
beat 120 on the carved box at every validation (bench/results/nyx_train_box/); 200 beat 170 side
by side for 35 minutes, one thread each, ahead by 0.10 to 0.16 dB at every validation after the
first and 26.63 against 26.43 dB on the 24 held-out frames with 3 % fewer steps
(bench/results/nyx_train_ab_resolution/), and its hour reached 27.49 dB against the 170 record's
27.32 (bench/results/nyx_train_r200_hour/). Finer does not pay in the hour: 230 was behind 200 by
0.49 to 0.59 dB over 25 minutes, on its own training rays too (bench/results/nyx_train_ab_resolution2/)."""
NYX_STEP_RATIO = 1.647
"""Training samples 1.647 voxels of the ``NYX_RESOLUTION`` grid apart: 0.0032 world units, the
spacing the 160-voxel trial ran at (1.4 voxels at 170). Other grids keep the world distance
(``nyx_step_ratio``); at 170, 1.7 voxels instead of 1.4 was behind by 0.13 to 0.32 dB."""


def nyx_step_ratio(resolution: int) -> float:
    """The recipe's training sample spacing in voxels of a ``resolution`` grid: the same world
    distance as ``NYX_STEP_RATIO`` at ``NYX_RESOLUTION``, so that a finer grid is compared at the
    same samples per ray (1.4 at 170, 1.894 at 230), rounded to 3 decimals as the reports record it."""
    return round(NYX_STEP_RATIO * resolution / NYX_RESOLUTION, 3)


NYX_BATCH_RAYS = 2048
"""Rays per step: half the paper's 4096. A step's cost is mostly per ray, so the hour makes about
1.7 times as many steps, and more, noisier steps fit Nyx faster than fewer, exacter ones. Two
40-minute runs side by side, one thread each (bench/results/nyx_train_ab_batch/): 25.61 against
25.10 dB on the 24 held-out frames, with 16780 against 9917 steps, ahead at every validation and
by more as the run went on (+0.25 dB at 5 minutes, +0.52 at 40). Halving again does not pay: 1024
rays led by 0.15 to 0.30 dB in a 20-minute trial (bench/results/nyx_train_ab_batch2/), but over 40
minutes 2048 rays led at every validation from 10 minutes on and ended 26.55 against 26.44 dB on
the 24 frames (bench/results/nyx_train_ab_batch3/)."""
NYX_VALIDATION_FRAMES = 6
"""Held-out frames of each periodic validation (the final evaluation renders ``--eval-frames``)."""
NYX_DENSITY_GRAD_KEEP = 0.125
"""Fraction of the near-empty density samples each step back-propagates (``TrainConfig.density_grad_keep``):
90 % of a trained step's density samples are near-empty (alpha below 1e-4). From the 27.10 dB
model, a step took 151.0 ms with every sample back-propagated and 117.7 ms with an eighth of the
near-empty ones (1.28x; bench/results/density_grad_speed.md); the run made 27710 iterations in
the hour against the 26.85 dB record's 23044."""
NYX_FACTOR_STORAGE = "int8"
"""Planes stored as int8 codes with row scales: the 26.85 dB record's 24 held-out frames rendered
26.8479 dB from it against 26.8486 dB from its float16 planes, in a 6.76 MB file instead of
12.17 MB (bench/results/factor_storage_int8.md)."""
NYX_TV_APPEARANCE = 0.0
"""No total variation on the appearance factors (the library keeps 0.01): Nyx's fit
is limited by capacity, not by noise (training frames score about as well as held-out ones). The
hour without it reached 27.32 dB / 0.950 on the 24 held-out frames (bench/results/
nyx_train_tv_appearance0_hour/), against 27.18 dB for the hour with it on the same CPU in another
session (nyx_train_b2048_run2/), ahead at every validation by 0.10 to 0.37 dB with 9 % fewer
steps; 35 minutes side by side, one thread each, it led at every validation too, by 0.05 to
0.25 dB (nyx_train_ab_tv_appearance/)."""
NYX_OCCUPANCY_REFINE_AT = (0.25, 0.5, 0.75)
"""Progress fractions at which the occupancy grid is rebuilt within itself
(``TrainConfig.occupancy_refine_at``)."""
NYX_OCCUPANCY_REFINE_DILATION = 0
"""Refined grids hold only the cells with content, not the one-cell ring around them
(``TrainConfig.occupancy_refine_dilation``): from the 27.10 dB model, a step evaluates 2.6 times
fewer density samples, 1.20 times faster steps, and its 24 held-out frames render 27.101 against
27.105 dB (bench/results/refine_dilation.md). The hour with it made 31875 iterations and reached
27.22 dB (bench/results/nyx_train_ring0/)."""

NYX_MICRO_BATCH_RAYS = 2048
NYX_MICRO_BATCH_SAMPLES = 131072
"""A step's 2048 rays rendered and back-propagated as one micro-batch where they evaluate at most
131072 samples (``TrainConfig.micro_batch_rays`` and ``micro_batch_samples``, the library's 4096
and 32768). The gradient is the same; each
micro-batch has fixed costs (per factor table a sort of its taps and a product into the whole
table's gradient, the decoders' weight gradients, the renderer's Python). When the micro-batches
still counted the samples in the rays' occupied windows (about 6 times those evaluated), the
library's limits split a late-phase step in four: from the 27.49 dB model it took 44.2 ms in one
micro-batch against 67.5 ms in four (1.53x). The hour with one (and ``NYX_WEIGHT_AVERAGE_SPAN``)
made 73167 steps against the 27.49 dB record's 52616 and reached 27.89 dB / 0.956 on the 24
held-out frames, peak RSS 1977 MB (bench/results/nyx_train_one_chunk_hour/). Counting the samples
evaluated, the library's limits take one micro-batch in the late phase too (38.5 ms against
45.5 ms at the former 1024-ray limit, bench/results/micro_batch_speed.md); the larger budget here
keeps the early phase, whose fog evaluates every sample, in fewer micro-batches."""
NYX_WEIGHT_AVERAGE_SPAN = 0.03
"""The parameters saved are their moving average over about the last 0.03 of the run
(``TrainConfig.weight_average_span``, kept from half-way on): from the 27.49 dB model, 10 more
minutes at the schedule's final rates rendered the 24 held-out frames 0.076 dB better from the
average than from the last parameters (27.631 against 27.555 dB; spans of 0.01 and 0.1: +0.058
and +0.080 dB; bench/results/nyx_weight_average.md)."""

NYX_LR_NETWORKS = 0.002
"""The decoders' starting learning rate, twice the paper's 0.001 (``TrainConfig.lr_networks``; the
factors keep 0.02). 30 minutes side by side on one thread each, it led at every validation by 0.03
to 0.32 dB, 26.62 against 26.37 dB on the 24 held-out frames (bench/results/
nyx_train_ab_lr_networks/); its hour reached 28.09 dB / 0.958 against the 27.89 dB record, ahead
at every validation by 0.11 to 0.29 dB (bench/results/nyx_train_lr_networks_hour/)."""

NYX_LATE_PHASE_STEP = {"batch_rays": NYX_BATCH_RAYS, "l1_switch_iteration": 0,
                       "density_grad_keep": NYX_DENSITY_GRAD_KEEP, "tv_weight_appearance": NYX_TV_APPEARANCE}
"""The recipe's step late in a run, as ``TrainConfig`` fields for ``late_phase_trainer``: its rays,
the L1 weight after the switch, the sampled density gradients, no appearance total variation."""


def late_phase_trainer(train, field, micro_batch_samples: int, **overrides) -> Trainer:  # noqa: ANN001
    """A trainer that steps a trained Nyx ``field`` as the late phase of a run does (its grid and
    occupancy, no milestones left, the recipe's sample spacing), for the step benchmarks;
    ``overrides`` are further ``TrainConfig`` fields."""
    res = field.resolution[0]
    cfg = TrainConfig(iterations=10**9, resolution_init=res, resolution_final=res, upsample_at=(), occupancy_at=(),
                      trim_every=10**9, micro_batch_samples=micro_batch_samples, **overrides)
    return Trainer(train, None, cfg, torch.device("cpu"), render_cfg=RenderConfig(step_ratio=nyx_step_ratio(res)), init_field=field)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def final_eval(ckpt: Path, val, n_frames: int, figure: Path | None = None,
               device: torch.device | None = None) -> dict:
    """Render ``n_frames`` evenly chosen held-out frames through the public inference API; with
    ``figure``, save the frame of median PSNR beside its ground truth and their CIELUV difference."""
    scene = load_scene(ckpt, device or torch.device("cpu"))
    rows = []
    for i in evenly_spaced(val.n_frames, n_frames):
        t0 = time.perf_counter()
        pred, gt = render_frame(scene, val, i, 256, 256)
        seconds = time.perf_counter() - t0
        held_setting = any(np.allclose(val.params[i].numpy(), s, atol=1e-6) for s in HOLDOUT_SETTINGS)
        rows.append({"frame": int(i), "psnr": psnr(pred, gt), "ssim": ssim(pred, gt), "seconds": seconds,
                     "held_out": "setting" if held_setting else "view", "images": (pred, gt)})
    if figure is not None:
        median = sorted(rows, key=lambda r: r["psnr"])[len(rows) // 2]
        pred, gt = median["images"]
        plot_difference(figure, pred, gt, luv_difference(pred, gt), EvalConfig.difference_scale_max,
                        f"held-out frame {median['frame']} (at a held-out {median['held_out']}), "
                        f"the median of {len(rows)}: {median['psnr']:.2f} dB")
    for r in rows:
        del r["images"]
    return {
        "frames": len(rows),
        "psnr": float(np.mean([r["psnr"] for r in rows])),
        "ssim": float(np.mean([r["ssim"] for r in rows])),
        "psnr_held_out_settings": float(np.mean([r["psnr"] for r in rows if r["held_out"] == "setting"] or [np.nan])),
        "psnr_held_out_views": float(np.mean([r["psnr"] for r in rows if r["held_out"] == "view"] or [np.nan])),
        "seconds_per_frame_256_median": float(np.median([r["seconds"] for r in rows])),
    }


def write_report(result: dict, out_dir: Path) -> None:
    write_json(out_dir / "nyx_train.json", result)
    f = result["final"]
    lines = [
        "# Nyx training on " + ("this CPU" if result.get("device", "cpu") == "cpu" else result["device"]),
        "",
        f"Command: `{result['command']}`  ",
        f"Machine: {result['machine']}",
        "",
        "| what | value |",
        "| --- | --- |",
        (f"| training budget | {result['budget_minutes']} min, space carving ({result['carve_seconds']} s) included, validation excluded |"
         if result.get("budget_minutes") else
         f"| training budget | {result['budget_iterations']} iterations ({result['train_seconds'] / 60:.1f} min) |"),
        f"| 1-min load average before / after | {result['load_average_before_after'][0]} / {result['load_average_before_after'][1]} |",
        f"| iterations | {result['iterations']} ({result['iterations_per_second']:.2f} it/s) |",
        f"| held-out PSNR / SSIM ({f['frames']} frames) | {f['psnr']:.2f} dB / {f['ssim']:.3f} |",
        f"| PSNR at held-out parameter settings | {f['psnr_held_out_settings']:.2f} dB |",
        f"| PSNR at held-out views | {f['psnr_held_out_views']:.2f} dB |",
        f"| peak RSS | {result['peak_rss_mb']:.0f} MB |",
        f"| checkpoint size | {result['checkpoint_mb']:.2f} MB |",
        f"| model box (after carving) | {result['box'][0]} to {result['box'][1]}, grid {result['final_resolution']} |",
        f"| recipe | {', '.join(f'{k} {v}' for k, v in result.get('recipe', {}).items())} |",
        f"| full-quality spacing chosen at the end | {result.get('full_spacing')} |",
        *([f"| inference grid | {g['cells']} cells, within the grid training last sampled; rebuilt from the density alone: "
           f"{g['unrestricted_cells']} cells, {g['unrestricted_psnr']:.2f} dB / {g['unrestricted_ssim']:.3f} on the same frames |"]
          if (g := result.get("final_grid")) else []),
        *([f"| parameters saved | their moving average (span {result['recipe']['weight_average_span']:g} of the run): "
           f"{w['average_val_psnr']:.2f} dB on the validation frames against {w['live_val_psnr']:.2f} dB from the last "
           "values, both before the final grid |"]
          if "live_val_psnr" in (w := result["log"][-1] if result.get("log") else {}) else []),
        f"| seconds per 256x256 frame (median) | {f['seconds_per_frame_256_median']:.2f} s |",
        "",
        "Validation PSNR against training time:",
        "",
        "| train s | iteration | train PSNR | val PSNR | val SSIM | grid | occupied cells |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in result["log"]:
        lines.append(f"| {row['train_seconds']:.0f} | {row['iteration']} | {row['train_psnr']:.2f} | "
                     f"{row.get('val_psnr', float('nan')):.2f} | {row.get('val_ssim', float('nan')):.3f} | "
                     f"{row.get('resolution', '')} | {row.get('occupied_cells', '')} |")
    lines += ["", "![validation PSNR against training time](nyx_train.png)", "",
              "![the held-out frame of median PSNR](nyx_heldout.png)", ""]
    (out_dir / "nyx_train.md").write_text("\n".join(lines))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 3.5))
        log = result["log"]
        ax.plot([r["train_seconds"] / 60 for r in log], [r.get("val_psnr", np.nan) for r in log], "o-", label="held-out")
        ax.plot([r["train_seconds"] / 60 for r in log], [r["train_psnr"] for r in log], "--", label="train (EMA)")
        ax.axhline(28.0, color="gray", lw=0.8, ls=":", label="target 28 dB")
        ax.set_xlabel("training minutes (2-core CPU)")
        ax.set_ylabel("PSNR (dB)")
        ax.legend()
        ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(out_dir / "nyx_train.png", dpi=110)
    except ImportError:
        pass


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "nyx"))
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--iterations", type=int, default=None,
                    help="schedule by this many iterations instead of --minutes (a GPU run, to see "
                         "what more iterations of the same recipe reach)")
    ap.add_argument("--device", default="cpu", help="cpu (default), cuda or auto")
    ap.add_argument("--batch-rays", type=positive_int, default=NYX_BATCH_RAYS,
                    help=f"rays per step (default {NYX_BATCH_RAYS}; the paper's is 4096)")
    ap.add_argument("--resolution", type=int, default=NYX_RESOLUTION,
                    help=f"final voxels per axis (default {NYX_RESOLUTION})")
    ap.add_argument("--validate-every", type=float, default=300.0, help="seconds of training")
    ap.add_argument("--eval-frames", type=int, default=24)
    ap.add_argument("--micro-batch-samples", type=positive_int, default=NYX_MICRO_BATCH_SAMPLES,
                    help="most samples back-propagated together (bounds activation memory; "
                         f"default {NYX_MICRO_BATCH_SAMPLES}, the library's {TrainConfig.micro_batch_samples})")
    ap.add_argument("--micro-batch-rays", type=positive_int, default=NYX_MICRO_BATCH_RAYS,
                    help=f"most rays per micro-batch (default {NYX_MICRO_BATCH_RAYS}, the library's {TrainConfig.micro_batch_rays})")
    ap.add_argument("--density-shift", type=float, default=FieldConfig.density_shift,
                    help=f"bias of the density activation of a fresh field (default {FieldConfig.density_shift:g})")
    ap.add_argument("--carve-min-seen-fraction", type=unit_fraction, default=NYX_CARVE_MIN_SEEN_FRACTION,
                    help="fraction of a setting's views that must see a carved cell "
                         f"(default {NYX_CARVE_MIN_SEEN_FRACTION:g}; 0 keeps every cell some view sees)")
    ap.add_argument("--param-components", type=int, default=FieldConfig.n_param_components,
                    help="components of each parameter-axis vector (default "
                         f"{FieldConfig.n_param_components}; must divide 16 and 48)")
    ap.add_argument("--appearance-components", type=positive_int, default=FieldConfig.n_appearance_components,
                    help="VM components per mode of the appearance grid (default "
                         f"{FieldConfig.n_appearance_components}; a multiple of --param-components)")
    ap.add_argument("--sh-degree", type=int, choices=range(4), default=FieldConfig.sh_degree,
                    help="spherical-harmonics degree (0..3) of the colour decoder's view-direction encoding "
                         f"(default {FieldConfig.sh_degree}; 0: colour does not depend on the view)")
    ap.add_argument("--upsample-at", type=parse_fractions, default=TrainConfig.upsample_at, metavar="P1,P2,...",
                    help="progress fractions at which the grid is upsampled, log-spaced from 64^3 to --resolution "
                         f"(default {','.join(map(str, TrainConfig.upsample_at))})")
    ap.add_argument("--occupancy-refine-at", type=parse_fractions,
                    default=NYX_OCCUPANCY_REFINE_AT, metavar="P1,P2,...",
                    help="progress fractions at which the occupancy grid is rebuilt within itself "
                         f"(default {','.join(map(str, NYX_OCCUPANCY_REFINE_AT))}; '' for none)")
    ap.add_argument("--occupancy-refine-dilation", type=non_negative_int, default=NYX_OCCUPANCY_REFINE_DILATION,
                    metavar="CELLS", help="cells by which a refined occupancy grid grows around its content "
                                          f"(default {NYX_OCCUPANCY_REFINE_DILATION})")
    ap.add_argument("--tv-density", type=non_negative_float, default=TrainConfig.tv_weight_density,
                    help=f"total-variation weight of the density factors (default {TrainConfig.tv_weight_density:g})")
    ap.add_argument("--tv-appearance", type=non_negative_float, default=NYX_TV_APPEARANCE,
                    help=f"total-variation weight of the appearance factors (default {NYX_TV_APPEARANCE:g}; "
                         f"the library's is {TrainConfig.tv_weight_appearance:g})")
    ap.add_argument("--density-grad-keep", type=unit_interval_open_below, default=NYX_DENSITY_GRAD_KEEP,
                    help="fraction of the near-empty density samples each step back-propagates "
                         f"(default {NYX_DENSITY_GRAD_KEEP:g}; 1: all)")
    ap.add_argument("--factor-storage", choices=sorted(FACTOR_STORAGE_DTYPES), default=NYX_FACTOR_STORAGE,
                    help=f"how the checkpoint stores the VM factors (default {NYX_FACTOR_STORAGE})")
    ap.add_argument("--step-ratio", type=positive_float, default=None,
                    help=f"training sample spacing in voxels (default: {NYX_STEP_RATIO:g} at {NYX_RESOLUTION}^3, "
                         "the same world distance at other resolutions)")
    add_learning_rate_args(ap, NYX_LR_NETWORKS)
    add_error_sampling_args(ap)
    add_weight_average_args(ap, NYX_WEIGHT_AVERAGE_SPAN)
    ap.add_argument("--lr-upsample-reset", action="store_true",
                    help="restart the learning-rate decay at each upsample (TrainConfig.lr_upsample_reset)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    ap.add_argument("--bbox", type=parse_bbox, default=None, metavar="X0,Y0,Z0,X1,Y1,Z1",
                    help="content box (write --bbox=-0.2,...); default: carved from the images")
    ap.add_argument("--figure-only", metavar="CKPT", default=None,
                    help="train nothing: write nyx_heldout.png for this checkpoint to --results")
    ap.add_argument("--out", default=str(ROOT / "runs" / "nyx.safetensors"))
    ap.add_argument("--results", default=None,
                    help="folder of the report (default bench/results/nyx_train_<stem of --out>)")
    ap.add_argument("--force", action="store_true", help="write over an existing --out and report")
    args = ap.parse_args()
    if args.results is None:
        args.results = str(ROOT / "bench" / "results" / f"nyx_train_{Path(args.out).stem}")
    if args.step_ratio is None:
        args.step_ratio = nyx_step_ratio(args.resolution)
    if not args.figure_only and not args.force:
        taken = [p for p in (Path(args.out), Path(args.results) / "nyx_train.json") if p.exists()]
        if taken:  # an hour of training must not end by writing over an earlier run
            ap.error(f"{' and '.join(map(str, taken))} already exist{'s' if len(taken) == 1 else ''}: "
                     "pass another --out / --results, or --force")

    try:  # a bad shape fails here, before the data loads, with FieldConfig's message
        field_cfg = FieldConfig(density_shift=args.density_shift, n_param_components=args.param_components,
                                n_appearance_components=args.appearance_components, sh_degree=args.sh_degree,
                                factor_storage=args.factor_storage)
    except ValueError as err:
        ap.error(str(err))
    device = pick_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    t0 = time.perf_counter()
    scene = with_bbox(load_dataset(args.data), args.bbox)
    load_s = time.perf_counter() - t0
    rss_after_load = peak_rss_mb()
    train, val = split_holdout(scene, holdout_for(scene))
    del scene
    assert val is not None
    if args.figure_only:
        Path(args.results).mkdir(parents=True, exist_ok=True)
        print(json.dumps(final_eval(Path(args.figure_only), val, args.eval_frames, Path(args.results) / "nyx_heldout.png")))
        return 0
    by_iterations = args.iterations is not None
    cfg = TrainConfig(iterations=args.iterations if by_iterations else 10**9,
                      time_budget_s=None if by_iterations else args.minutes * 60, batch_rays=args.batch_rays,
                      micro_batch_samples=args.micro_batch_samples, micro_batch_rays=args.micro_batch_rays, resolution_final=args.resolution,
                      validate_every_s=args.validate_every, validate_max_images=NYX_VALIDATION_FRAMES,
                      carve_min_seen_fraction=args.carve_min_seen_fraction, tv_weight_density=args.tv_density,
                      tv_weight_appearance=args.tv_appearance,
                      occupancy_refine_at=args.occupancy_refine_at, density_grad_keep=args.density_grad_keep,
                      occupancy_refine_dilation=args.occupancy_refine_dilation,
                      lr_factors=args.lr_factors, lr_networks=args.lr_networks, lr_decay_ratio=args.lr_decay_ratio,
                      upsample_at=args.upsample_at, lr_upsample_reset=args.lr_upsample_reset, error_sampling_tile=args.error_sampling_tile,
                      error_sampling_uniform=args.error_sampling_uniform,
                      weight_average_span=args.weight_average_span, weight_average_from=args.weight_average_from)
    trainer = Trainer(train, val, cfg, device, field_cfg=field_cfg, render_cfg=RenderConfig(step_ratio=args.step_ratio))
    trainer.run(progress_bar=sys.stderr.isatty(), on_validate=lambda row: print(json.dumps(row), flush=True))
    ckpt = trainer.save(args.out, dataset="shared/data/nyx")
    out_dir = Path(args.results)
    out_dir.mkdir(parents=True, exist_ok=True)
    final = final_eval(ckpt, val, args.eval_frames, out_dir / "nyx_heldout.png", device)
    # The same trained field with the inference grid the trainer built before finish_occupancy:
    # the density's occupancy now, not limited to the cells training last sampled.
    kept = trainer.field.occupancy
    trainer.update_occupancy(shrink=False)
    other = trainer.save(Path(args.out).with_name(Path(args.out).stem + "_unrestricted.safetensors"), dataset="shared/data/nyx")
    unrestricted = final_eval(other, val, args.eval_frames, None, device)
    grids = {"cells": None if kept is None else int(kept.sum()),
             "unrestricted_cells": int(trainer.field.occupancy.sum()), "unrestricted_psnr": unrestricted["psnr"],
             "unrestricted_ssim": unrestricted["ssim"]}
    trainer.field.set_occupancy(kept)
    threads = torch.get_num_threads()
    result = {
        "command": "python bench/nyx_train.py " + " ".join(sys.argv[1:]),
        "machine": (f"{cpu_description()}, {threads} thread{'' if threads == 1 else 's'}, torch {torch.__version__}"
                    + (f", {torch.cuda.get_device_name(device)}" if device.type == "cuda" else "")),
        "device": device.type,
        "budget_minutes": None if by_iterations else args.minutes,
        "budget_iterations": args.iterations,
        "train_frames": train.n_frames,
        "val_frames": val.n_frames,
        "holdout_settings": HOLDOUT_SETTINGS,
        "holdout_views": HOLDOUT_VIEWS,
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "load_average_before_after": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
        "carve_seconds": round(trainer.setup_seconds, 1),
        "load_seconds": round(load_s, 1),
        "rss_after_load_mb": round(rss_after_load, 0),
        "iterations": trainer.state.iteration,
        "iterations_per_second": trainer.state.iteration / max(trainer.state.train_seconds, 1e-9),
        "train_seconds": trainer.state.train_seconds,
        "peak_rss_mb": peak_rss_mb(),
        "checkpoint_mb": ckpt.stat().st_size / 1e6,
        "final_resolution": trainer.field.resolution,
        "recipe": {"carve_min_seen_fraction": args.carve_min_seen_fraction, "resolution": args.resolution,
                   "step_ratio": args.step_ratio, "batch_rays": args.batch_rays, "param_components": args.param_components,
                   "appearance_components": args.appearance_components, "sh_degree": args.sh_degree,
                   "tv_density": cfg.tv_weight_density, "tv_appearance": cfg.tv_weight_appearance,
                   "occupancy_refine_at": list(args.occupancy_refine_at),
                   "occupancy_refine_dilation": cfg.occupancy_refine_dilation, "full_step_ratio": trainer.render_cfg.full_step_ratio,
                   "factor_storage": trainer.field.cfg.factor_storage, "density_grad_keep": cfg.density_grad_keep,
                   "lr_factors": cfg.lr_factors, "lr_networks": cfg.lr_networks, "lr_decay_ratio": cfg.lr_decay_ratio,
                   "upsample_at": list(cfg.upsample_at),
                   "lr_upsample_reset": cfg.lr_upsample_reset, "error_sampling_tile": cfg.error_sampling_tile,
                   "error_sampling_uniform": cfg.error_sampling_uniform,
                   "weight_average_span": cfg.weight_average_span, "weight_average_from": cfg.weight_average_from,
                   "micro_batch_rays": cfg.micro_batch_rays, "micro_batch_samples": cfg.micro_batch_samples},
        "full_spacing": trainer.spacing_note,
        "final_grid": grids,
        "box": [[round(float(x), 4) for x in row] for row in trainer.field.aabb.cpu()],
        "final": final,
        "log": trainer.state.log,
    }
    write_report(result, out_dir)
    print(json.dumps({k: v for k, v in result.items() if k != "log"}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
