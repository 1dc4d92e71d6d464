"""How far a trained Nyx model is from the frames it was trained on, against the held-out ones.

Renders ``--frames`` evenly chosen training frames and as many held-out frames (the hold-out of
bench/nyx_train.py) through the public inference API at 256x256, and records PSNR and SSIM of
each set. Held-out frames as good as the training frames mean the model does not overfit: what
it lacks, it lacks on the training frames too (fit, not generalisation).

    .venv/bin/python bench/nyx_fit_gap.py --checkpoint runs/nyx.safetensors

Writes bench/results/nyx_fit_gap.{json,md} (``--results``).
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from bench_common import (
    add_trained_model_args,
    evenly_spaced,
    fmt,
    load_average,
    machine_record,
    markdown_header,
    nyx_split,
    render_frame,
    require_checkpoint,
    write_results,
)

from visnerf.data.scene import SceneData
from visnerf.evaluation.metrics import psnr, ssim
from visnerf.inference import load_scene


def evaluate_frames(scene, frames: SceneData, count: int) -> dict:  # noqa: ANN001
    """Mean and per-frame PSNR / SSIM of ``count`` evenly chosen ``frames`` rendered by ``scene``."""
    rows = []
    for i in evenly_spaced(frames.n_frames, count):
        pred, gt = render_frame(scene, frames, i, frames.intrinsics.width, frames.intrinsics.height)
        rows.append({"frame": int(i), "psnr": psnr(pred, gt), "ssim": ssim(pred, gt)})
    return {"frames": len(rows), "psnr": float(np.mean([r["psnr"] for r in rows])),
            "ssim": float(np.mean([r["ssim"] for r in rows])),
            "psnr_min": float(np.min([r["psnr"] for r in rows])),
            "psnr_max": float(np.max([r["psnr"] for r in rows])), "per_frame": rows}


def write_markdown(path: Path, record: dict) -> None:
    t, v = record["train_frames"], record["held_out_frames"]
    lines = markdown_header("Nyx: the trained model on its training frames and on held-out frames", record) + [
        "",
        f"Checkpoint: `{record['checkpoint']}`",
        "",
        "| frames | count | PSNR (mean) | PSNR (min .. max) | SSIM (mean) |",
        "| --- | --- | --- | --- | --- |",
        f"| training | {t['frames']} | {fmt(t['psnr'], 2)} dB | {fmt(t['psnr_min'], 1)} .. {fmt(t['psnr_max'], 1)} | {fmt(t['ssim'], 3)} |",
        f"| held out | {v['frames']} | {fmt(v['psnr'], 2)} dB | {fmt(v['psnr_min'], 1)} .. {fmt(v['psnr_max'], 1)} | {fmt(v['ssim'], 3)} |",
        "",
        f"Gap (training minus held out): {record['gap_db']:.2f} dB.",
        "",
    ]
    path.write_text("\n".join(lines))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_trained_model_args(ap, "nyx.safetensors")
    ap.add_argument("--frames", type=int, default=24, help="frames of each set (default 24)")
    args = ap.parse_args()
    require_checkpoint(ap, args.checkpoint)
    load_before = load_average()
    train, val = nyx_split(args.data)
    scene = load_scene(Path(args.checkpoint), torch.device("cpu"))
    t0 = time.perf_counter()
    train_eval = evaluate_frames(scene, train, args.frames)
    val_eval = evaluate_frames(scene, val, args.frames)
    record = {
        **machine_record(),
        "command": "python bench/nyx_fit_gap.py " + " ".join(sys.argv[1:]),
        "load_average_1min": {"before": load_before, "after": load_average()},
        "checkpoint": args.checkpoint,
        "seconds": round(time.perf_counter() - t0, 1),
        "train_frames": train_eval,
        "held_out_frames": val_eval,
        "gap_db": train_eval["psnr"] - val_eval["psnr"],
    }
    write_results(Path(args.results), "nyx_fit_gap", record, write_markdown)
    print(f"training frames {train_eval['psnr']:.2f} dB, held out {val_eval['psnr']:.2f} dB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
