"""Where a trained Nyx model's squared error sits among the pixels of its training frames.

Renders ``--frames`` evenly chosen training frames at 256x256 through the public inference API and
records: the fraction of each frame that is background; the share of the squared error held by the
worst 1, 5, 10, 20 and 50 % of the pixels; and, for tiles of 1 to 16 pixels a side, how many times
lower the second moment of the gradient estimate would be if pixels were drawn in proportion to
the root of their tile's error (a fraction ``--uniform`` of the draw kept uniform), each weighted
by its inverse probability, than if they were drawn uniformly. The error is taken as known
exactly and the gradient as proportional to the residual, so the ratio is the most such a draw
(``TrainConfig.error_sampling_tile``) could gain per ray, before its cost.

    .venv/bin/python bench/nyx_error_concentration.py --checkpoint runs/nyx_hour_r200.safetensors

Writes bench/results/nyx_error_concentration.{json,md} (``--results``).
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

from visnerf.data.error_map import ErrorMapConfig, PixelErrorMap
from visnerf.evaluation.metrics import psnr
from visnerf.inference import load_scene

WORST_FRACTIONS = (0.01, 0.05, 0.1, 0.2, 0.5)
TILE_SIDES = (1, 2, 4, 8, 16)


def error_share_of_worst(errors: np.ndarray, fraction: float) -> float:
    """Share of ``errors.sum()`` held by the largest ``fraction`` of the values."""
    ordered = np.sort(errors.ravel())[::-1]
    count = max(1, int(round(fraction * ordered.size)))
    total = float(ordered.sum())
    return float(ordered[:count].sum()) / total if total > 0 else 0.0


def second_moment_ratio(errors: np.ndarray, tile: int, uniform: float) -> float:
    """Uniform draw's second moment over the root-error draw's, with tiles of ``tile`` pixels a side.

    The draw is the training's own (``PixelErrorMap.tile_masses``) with each tile's estimate set to
    its pixels' mean error. With per-pixel squared errors ``e`` and a tile ``t`` holding
    ``S_t = sum e``, a draw of tile probabilities ``p_t`` (uniform within the tile) weighted by
    ``1 / p`` has second moment proportional to ``sum_t S_t / p_t``: ``T * sum S`` for the uniform
    draw's ``p_t = 1 / T``."""
    f, h, w = errors.shape
    if h % tile or w % tile:
        raise ValueError(f"{h}x{w} frames do not split into {tile}-pixel tiles")
    sums = errors.reshape(f, h // tile, tile, w // tile, tile).sum(axis=(2, 4)).ravel().astype(np.float64)
    error_map = PixelErrorMap(f, h, w, ErrorMapConfig(tile=tile, uniform=uniform))
    error_map.error = torch.from_numpy(sums / (tile * tile)).float()
    p = error_map.tile_masses().double().numpy()
    return float(sums.size * sums.sum() / (sums / p).sum())


def write_markdown(path: Path, record: dict) -> None:
    lines = markdown_header("Nyx: where the squared error sits among a trained model's training pixels", record) + [
        "",
        f"Checkpoint: `{record['checkpoint']}`; {record['frames']} training frames "
        f"({', '.join(str(i) for i in record['frame_indices'])}).",
        "",
        "| frame | PSNR | background fraction |",
        "| --- | --- | --- |",
        *[f"| {r['frame']} | {fmt(r['psnr'], 2)} dB | {fmt(r['background_fraction'], 3)} |" for r in record["per_frame"]],
        "",
        "| worst pixels | share of the squared error |",
        "| --- | --- |",
        *[f"| {fmt(100 * float(k), 0)} % | {fmt(v, 3)} |" for k, v in record["error_share_of_worst"].items()],
        "",
        f"Drawing pixels by the root of their tile's (known) error, {fmt(100 * record['uniform'], 0)} % of the draw "
        "uniform, each weighted by its inverse probability: the uniform draw's gradient second moment over that draw's.",
        "",
        "| tile side | second moment, uniform over error-drawn |",
        "| --- | --- |",
        *[f"| {k} px | {fmt(v, 2)}x |" for k, v in record["second_moment_ratio"].items()],
        "",
    ]
    path.write_text("\n".join(lines))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_trained_model_args(ap, "nyx_hour_r200.safetensors")
    ap.add_argument("--frames", type=int, default=8, help="training frames to render (default 8)")
    ap.add_argument("--uniform", type=float, default=0.2, help="uniform share of the draw (default 0.2)")
    args = ap.parse_args()
    require_checkpoint(ap, args.checkpoint)
    if not 0.0 < args.uniform <= 1.0:
        ap.error(f"--uniform must be in (0, 1], got {args.uniform}")
    load_before = load_average()
    train, _ = nyx_split(args.data)
    scene = load_scene(Path(args.checkpoint), torch.device("cpu"))
    background = np.asarray(train.background, dtype=np.float32)
    t0 = time.perf_counter()
    indices = evenly_spaced(train.n_frames, args.frames)
    errors, rows = [], []
    for i in indices:
        pred, gt = render_frame(scene, train, i, train.intrinsics.width, train.intrinsics.height)
        e = ((pred - gt) ** 2).mean(-1)  # [h, w]
        errors.append(e)
        rows.append({"frame": int(i), "psnr": psnr(pred, gt),
                     "background_fraction": float((np.abs(gt - background).max(-1) < 1e-3).mean())})
    stack = np.stack(errors)
    record = {
        **machine_record(),
        "command": "python bench/nyx_error_concentration.py " + " ".join(sys.argv[1:]),
        "load_average_1min": {"before": load_before, "after": load_average()},
        "checkpoint": args.checkpoint,
        "seconds": round(time.perf_counter() - t0, 1),
        "frames": len(indices),
        "frame_indices": [int(i) for i in indices],
        "uniform": args.uniform,
        "per_frame": rows,
        "error_share_of_worst": {str(f): error_share_of_worst(stack, f) for f in WORST_FRACTIONS},
        "second_moment_ratio": {str(k): second_moment_ratio(stack, k, args.uniform) for k in TILE_SIDES},
    }
    write_results(Path(args.results), "nyx_error_concentration", record, write_markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
