"""``visnerf eval``: measure a checkpoint against ground truth and report error with run time."""

import argparse
import sys
from pathlib import Path

from visnerf.arg_types import add_device_option
from visnerf.checkpoint import CheckpointError
from visnerf.cinema_options import add_cinema_options, cinema_camera
from visnerf.data.datasets import SPLITS
from visnerf.evaluation.colour_difference import DIFFERENCE_SCALE_MAX
from visnerf.evaluation.ground_truth import EvaluationError
from visnerf.evaluation.perceptual import LpipsConfig
from visnerf.evaluation.sweeps import SweepConfig


def _frame_list(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"cannot read frame indices {text!r}: use '0,90,180'") from None


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``eval`` sub-command."""
    p = sub.add_parser(
        "eval",
        help="measure a checkpoint against ground-truth images; report error with render and training time",
        description="Render every frame of a dataset split, compare it with the ground truth (PSNR, SSIM, "
        "LPIPS where its weights are stored locally, CIELUV difference images), split the error by place in "
        "parameter space, sweep render settings (PSNR against ms per frame) and plot the training log "
        "(PSNR against training time). Writes report.md, summary.json, CSV files and PNG figures.",
    )
    p.add_argument("checkpoint", help="checkpoint (.safetensors)")
    p.add_argument("data", help="dataset folder with transforms_<split>.json, or a Cinema database (every row scored)")
    p.add_argument("--split", choices=SPLITS, default=None,
                   help="split to evaluate (default test; a Cinema database has none)")
    p.add_argument("--out", required=True, type=Path, help="report folder (created; files in it are replaced)")
    p.add_argument("--quality", choices=("full", "preview"), default="full", help="render quality (default full)")
    p.add_argument("--max-frames", type=int, default=None, metavar="N",
                   help="evaluate N evenly chosen frames instead of every frame")
    p.add_argument("--diff-frames", type=_frame_list, default=(), metavar="I,J,..",
                   help="frames shown as difference images (default: worst, median and best PSNR)")
    p.add_argument("--diff-scale", type=float, default=DIFFERENCE_SCALE_MAX, metavar="DELTA_E",
                   help=f"top of the difference legend in CIELUV Delta E*uv (default {DIFFERENCE_SCALE_MAX:g})")
    p.add_argument("--lpips-weights", type=Path, default=None, metavar="PATH",
                   help="LPIPS backbone weights stored locally (torchvision state dict); without them, "
                   "the report says LPIPS was not computed")
    p.add_argument("--lpips-net", choices=("alex", "vgg", "squeeze"), default="alex")
    p.add_argument("--train-log", type=Path, action="append", default=[], metavar="LOG",
                   help="training log (.log.csv or .log.json) of another run to plot; repeatable")
    p.add_argument("--sweep-frames", type=int, default=SweepConfig.n_frames, metavar="N",
                   help=f"frames rendered per render setting in the sweep (default {SweepConfig.n_frames})")
    p.add_argument("--no-sweep", action="store_true", help="skip the render-settings sweep")
    add_device_option(p)
    add_cinema_options(p)
    p.set_defaults(func=eval_command, requires=("skimage", "matplotlib"))  # SSIM, report figures


def eval_command(args: argparse.Namespace) -> int:
    """Exit code 0, or 2 with ``error: ...`` on stderr for bad input."""
    from visnerf.evaluation.evaluate import EvalConfig, evaluate_checkpoint
    from visnerf.evaluation.report import write_report
    from visnerf.runtime import pick_device

    if args.max_frames is not None and args.max_frames < 1:
        print(f"error: --max-frames must be at least 1, got {args.max_frames}", file=sys.stderr)
        return 2
    if not args.diff_scale > 0:
        print(f"error: --diff-scale must be positive, got {args.diff_scale}", file=sys.stderr)
        return 2
    if args.sweep_frames < 1:
        print(f"error: --sweep-frames must be at least 1, got {args.sweep_frames}", file=sys.stderr)
        return 2
    if args.out.exists() and not args.out.is_dir():
        print(f"error: --out {args.out} exists and is not a folder", file=sys.stderr)
        return 2
    try:
        cinema = cinema_camera(args)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    cfg = EvalConfig(
        split=args.split, cinema=cinema, quality=args.quality, max_frames=args.max_frames,
        difference_frames=args.diff_frames,
        difference_scale_max=float(args.diff_scale), lpips=LpipsConfig(args.lpips_weights, args.lpips_net),
        sweep=SweepConfig(enabled=not args.no_sweep, n_frames=args.sweep_frames),
        training_logs=tuple(args.train_log),
    )  # fmt: skip
    try:
        device = pick_device(args.device)
        result = evaluate_checkpoint(args.checkpoint, args.data, cfg, device)
        summary = write_report(result, cfg, args.out)
    except (CheckpointError, EvaluationError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    m = summary["metrics"]
    lpips = "n/a" if m["lpips"] is None else f"{m['lpips']:.4f}"
    psnr = f"{m['psnr']:.2f}" if isinstance(m["psnr"], float) else m["psnr"]
    print(f"{m['n']} frames of {result.split}: PSNR {psnr} dB, SSIM {m['ssim']:.4f}, LPIPS {lpips}, "
          f"{m['ms_median']:.0f} ms per frame; report in {args.out / 'report.md'}")
    return 0
