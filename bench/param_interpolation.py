"""Parameter tables between training values: piecewise-linear against the monotone cubic.

Training sees the parameter tables only at their knots (the training values), where both
interpolants give the row itself; they differ only between training values, which is where every
frame of the synthetic scenes' test paths lies. For each checkpoint, renders its whole test path at
full quality twice, the tables interpolated piecewise-linearly (the paper's scheme, reproduced
here) and by the product's monotone cubic (``representation.param_axes.interpolate_knots``), and
reports mean PSNR and SSIM against the ground truth and the worst frame. (Frame times are not
compared here: the interpolant runs once a frame, and the two passes run one after the other.)

Nyx has ground truth only at its training values. ``--nyx CKPT --nyx-axis NAME`` scores a model
trained with the middle value of that axis held out (``bench/nyx_train.py --middle-axis NAME``) on
``--nyx-frames`` frames at that value, from all views: between two training values, where
the interpolants differ (an axis with five values keeps four knots, so the cubic has a curve to
follow; one with three keeps two, where both interpolants are the same line).

    .venv/bin/python bench/param_interpolation.py --scenes plume_time tangle_iso vortex_tf1 vortex_tf2 cosmo_sim \
        --nyx runs/nyx_middle_p2.safetensors --nyx-axis p2
"""

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from bench_common import RESULTS, ROOT, evenly_spaced, fmt, machine_record, middle_holdout, write_results
from jaxtyping import Float
from torch import Tensor

from visnerf.data.holdout import held_out_kind, split_holdout
from visnerf.data.parsers.blender import load_dataset
from visnerf.data.scene import SceneData
from visnerf.evaluation.frames import normalize_params, render_frame
from visnerf.evaluation.ground_truth import load_ground_truth
from visnerf.evaluation.metrics import psnr, ssim
from visnerf.inference import load_scene
from visnerf.rendering.renderer import RenderSettings
from visnerf.representation import param_axes


def piecewise_linear(table: Float[Tensor, "m c"], knots: Float[Tensor, " m"], x: Float[Tensor, " n"]) -> Float[Tensor, "n c"]:
    """The tables' interpolation before the monotone cubic: straight between neighbouring knots."""
    m = knots.shape[0]
    if m == 1:
        return table.expand(x.shape[0], -1)
    x = x.clamp(float(knots[0]), float(knots[-1]))
    hi = torch.searchsorted(knots, x.contiguous()).clamp(1, m - 1)
    lo = hi - 1
    frac = ((x - knots[lo]) / (knots[hi] - knots[lo])).clamp(0.0, 1.0).unsqueeze(-1)
    return table[lo] * (1.0 - frac) + table[hi] * frac


INTERPOLANTS = {"piecewise linear": piecewise_linear, "monotone cubic": param_axes.interpolate_knots}


def test_path(checkpoint: Path, data: Path) -> tuple[SceneData, list[int]]:
    """The synthetic scene's whole test path."""
    gt = load_ground_truth(data, "test", load_scene(checkpoint).meta.param_axes).scene
    return gt, list(range(gt.n_frames))


def nyx_middle_frames(data: Path, axis: str, count: int) -> tuple[SceneData, list[int]]:
    """``count`` frames at the held-out middle value of ``axis`` (from every view)."""
    scene = load_dataset(data)
    holdout = middle_holdout(scene, axis)
    held = split_holdout(scene, holdout)[1]
    if held is None:
        raise ValueError(f"{data}: the hold-out {holdout} leaves no frame out")
    kinds = held_out_kind(held, holdout)
    middle = [i for i, kind in enumerate(kinds) if kind == "axis_value"]
    return held, [middle[i] for i in evenly_spaced(len(middle), count)]


def score(checkpoint: Path, gt: SceneData, frames: list[int]) -> dict[str, dict[str, float]]:
    scene = load_scene(checkpoint)
    settings = RenderSettings.from_meta(scene.meta, "full")
    params = torch.stack([normalize_params(scene.meta.param_axes, row) for row in gt.params])
    product = param_axes.interpolate_knots
    out = {}
    try:
        for label, interpolant in INTERPOLANTS.items():
            param_axes.interpolate_knots = interpolant
            render_frame(scene.field, gt.c2w[frames[0]], gt.intrinsics, params[frames[0]], settings)  # warm-up
            dbs, sims = [], []
            for i in frames:
                frame = render_frame(scene.field, gt.c2w[i], gt.intrinsics, params[i], settings)
                real = gt.images[i].numpy().astype(np.float32) / 255.0
                dbs.append(psnr(frame.rgb, real))
                sims.append(ssim(frame.rgb, real))
            out[label] = {"psnr": float(np.mean(dbs)), "ssim": float(np.mean(sims)), "worst_psnr": float(min(dbs)),
                          "frames": len(frames)}
            print(checkpoint.name, label, out[label], file=sys.stderr)
    finally:
        param_axes.interpolate_knots = product
    return out


def write_markdown(path: Path, record: dict) -> None:
    lines = ["# Parameter tables between training values: piecewise linear against the monotone cubic", "",
             f"Command: `{record['command']}`  ",
             f"Machine: {record['machine']}, torch {record['torch']}, {record['torch_threads']} torch thread(s), "
             f"{record['date']}.", "",
             "Each checkpoint rendered at full quality on the frames named, every one between training values, "
             "once per interpolant of the parameter tables. PSNR and SSIM: means over the frames; worst: the "
             "lowest frame PSNR.", "",
             "| checkpoint | K | frames | piecewise linear PSNR / SSIM (worst) | monotone cubic PSNR / SSIM (worst) | "
             "delta dB |",
             "| --- | --- | --- | --- | --- | --- |"]
    for r in record["rows"]:
        a, b = r["piecewise linear"], r["monotone cubic"]
        lines.append(f"| {r['checkpoint']} | {r['K']} | {r['frames']}, {r['size']} | {fmt(a['psnr'], 2)} / {fmt(a['ssim'], 4)} ({fmt(a['worst_psnr'], 2)}) "
                     f"| {fmt(b['psnr'], 2)} / {fmt(b['ssim'], 4)} ({fmt(b['worst_psnr'], 2)}) "
                     f"| {b['psnr'] - a['psnr']:+.2f} |")
    lines += ["", record["note"]]
    path.write_text("\n".join(lines) + "\n")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["plume_time", "tangle_iso", "vortex_tf1", "vortex_tf2", "cosmo_sim"])
    ap.add_argument("--checkpoints", type=Path, default=ROOT / "runs" / "eval",
                    help="folder of NAME.safetensors (bench/eval_scenes.py's work folder)")
    ap.add_argument("--data-root", type=Path, default=ROOT / "data" / "eval", help="folder of NAME_128 datasets")
    ap.add_argument("--nyx", type=Path, default=None, metavar="CKPT", help="a Nyx model trained without a middle value")
    ap.add_argument("--nyx-axis", default=None, metavar="NAME", help="the axis of that middle value")
    ap.add_argument("--nyx-data", type=Path, default=ROOT.parent / "shared" / "data" / "nyx")
    ap.add_argument("--nyx-frames", type=int, default=24)
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args()
    if args.nyx is not None and args.nyx_axis is None:
        ap.error("--nyx needs --nyx-axis, the axis whose middle value the model was trained without")
    jobs = [(args.checkpoints / f"{name}.safetensors", "test path",
             lambda c, name=name: test_path(c, args.data_root / f"{name}_128")) for name in args.scenes]
    if args.nyx is not None:
        jobs.append((args.nyx, f"{args.nyx_frames} frames at the middle {args.nyx_axis} held out",
                     lambda c: nyx_middle_frames(args.nyx_data, args.nyx_axis, args.nyx_frames)))
    rows = []
    for checkpoint, frames_label, frames_of in jobs:
        gt, frames = frames_of(checkpoint)
        result = score(checkpoint, gt, frames)
        k = len(load_scene(checkpoint).meta.param_axes)
        rows.append({"checkpoint": str(checkpoint.relative_to(ROOT)) if checkpoint.is_relative_to(ROOT) else str(checkpoint),
                     "K": k, "frames": frames_label, "size": f"{gt.intrinsics.width}x{gt.intrinsics.height}", **result})
    record = {
        "command": "python bench/param_interpolation.py " + " ".join(sys.argv[1:]), **machine_record(), "rows": rows,
        "note": "The synthetic scenes' checkpoints are bench/eval_scenes.py's (10 minutes each with the product's "
                "defaults); those of plume_time, tangle_iso, vortex_tf1 and cosmo_sim are the bundled ones. Nyx has "
                "ground truth only at its training values, where both interpolants agree: "
                + (f"its row is a model trained by `bench/nyx_train.py --middle-axis {args.nyx_axis}`, scored at "
                   "that held-out middle value." if args.nyx is not None else "not scored here."),
    }
    write_results(args.results, "param_interpolation", record, write_markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
