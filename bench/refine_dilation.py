"""A refined occupancy grid with and without its one-cell ring (``TrainConfig.occupancy_refine_dilation``).

From a trained Nyx checkpoint (its grid refined with one cell of dilation), the grid is refined
once more within itself as a refine milestone would, with the ring (1) and without it (0). For
each grid: cells, held-out PSNR / SSIM of frames rendered with it (the training validation's
renderer, before any step is taken), and the time and density samples of a training step, one
trainer per grid stepping its own copy of the field (the Nyx recipe's sampled density gradients), alternating over ``--rounds`` so that both
share the machine's noise.

    python bench/refine_dilation.py --checkpoint runs/nyx_sampled.safetensors

Writes bench/results/refine_dilation.{json,md}.
"""

import argparse
import copy
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import torch
from bench_common import (
    add_step_timing_args,
    add_trained_model_args,
    alternate_steps,
    load_average,
    machine_record,
    markdown_header,
    nyx_split,
    step_time_summary,
    write_results,
)
from nyx_train import NYX_DENSITY_GRAD_KEEP, late_phase_trainer

from visnerf.checkpoint import load_checkpoint
from visnerf.training.trainer import validate

DILATIONS = (1, 0)


def write_markdown(path: Path, record: dict[str, Any]) -> None:
    lines = [*markdown_header("Refined occupancy grid with and without its one-cell ring", record),
             f"Checkpoint: `{record['checkpoint']}` (grid {record['resolution']}, occupancy {record['occupancy_shape']}); "
             f"held-out frames: {record['frames']}; steps: {record['rounds']} rounds of {record['steps']} per grid, "
             "alternating.", "",
             "| dilation | occupied cells | refine s | held-out PSNR | SSIM | ms per frame | density samples per step "
             "| median ms per step | min | max | speed-up (medians) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    base = record["results"][0]["median_ms"]
    for r in record["results"]:
        lines.append(f"| {r['dilation']} | {r['cells']} | {r['refine_seconds']:.1f} | {r['val_psnr']:.3f} dB | "
                     f"{r['val_ssim']:.4f} | {r['val_ms_per_frame']:.0f} | {r['samples_per_step']:.0f} | "
                     f"{r['median_ms']:.1f} | {r['min_ms']:.1f} | {r['max_ms']:.1f} | {base / r['median_ms']:.2f}x |")
    lines.append("")
    path.write_text("\n".join(lines))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_trained_model_args(ap, "nyx_sampled.safetensors")
    add_step_timing_args(ap, steps=4, per="grid")
    ap.add_argument("--frames", type=int, default=24, help="held-out frames rendered with each grid")
    args = ap.parse_args()
    load_before = load_average()
    train, val = nyx_split(args.data)
    field, meta = load_checkpoint(args.checkpoint, torch.device("cpu"))
    if field.occupancy is None:
        ap.error(f"{args.checkpoint} has no occupancy grid to refine")
    trainers, rows = {}, {}
    for dilation in DILATIONS:
        own = copy.deepcopy(field)
        trainer = late_phase_trainer(train, own, args.micro_batch_samples, occupancy_refine_dilation=dilation,
                                     density_grad_keep=NYX_DENSITY_GRAD_KEEP)
        t0 = time.perf_counter()
        trainer.refine_occupancy()
        refine_s = time.perf_counter() - t0
        assert own.occupancy is not None
        held_out = validate(own, val, meta.render, args.frames)
        rows[dilation] = {"dilation": dilation, "cells": int(own.occupancy.sum()), "refine_seconds": refine_s,
                          **held_out}
        trainer.train_step()  # warm-up
        trainers[dilation] = trainer
    times, outputs = alternate_steps(trainers, args.rounds, args.steps)
    results = [{**rows[d], **step_time_summary(times[d]),
                "samples_per_step": statistics.mean(out["samples"] for out in outputs[d])} for d in DILATIONS]
    record = {
        **machine_record(),
        "command": " ".join(["python bench/refine_dilation.py", *sys.argv[1:]]),
        "load_average_1min": {"before": load_before, "after": load_average()},
        "checkpoint": args.checkpoint, "resolution": list(field.resolution),
        "occupancy_shape": list(field.occupancy.shape), "frames": min(args.frames, val.n_frames),
        "rounds": args.rounds, "steps": args.steps, "results": results,
    }
    write_results(Path(args.results), "refine_dilation", record, write_markdown)
    for r in results:
        print(f"dilation {r['dilation']}: {r['cells']} cells, {r['val_psnr']:.3f} dB, "
              f"{r['samples_per_step']:.0f} samples, {r['median_ms']:.1f} ms per step")
    return 0


if __name__ == "__main__":
    sys.exit(main())
