"""Does the parameters' moving average render better than their last values, at the end of a run?

Steps a trained Nyx model on as the end of the hour does (the recipe's step and priors, the
learning rates at the schedule's final ``--lr-scale``) for ``--minutes``, keeping a moving
average of its parameters for each of ``--spans`` (``training/weight_average.py``; a span is a
fraction of a 60-minute run, as ``TrainConfig.weight_average_span``). Then renders the same
held-out frames (the hold-out of bench/nyx_train.py) through the public inference API from the
checkpoint as loaded, from the last parameters and from each average: one run, so every variant
has the same steps and the same machine.

    .venv/bin/python bench/nyx_weight_average.py --checkpoint runs/nyx_hour_r200.safetensors

Writes bench/results/nyx_weight_average.{json,md} (``--results``).
"""

import argparse
import sys
import time
from pathlib import Path

import torch
from bench_common import (
    add_trained_model_args,
    fmt,
    load_average,
    machine_record,
    markdown_header,
    nyx_split,
    require_checkpoint,
    write_results,
)
from nyx_fit_gap import evaluate_frames
from nyx_train import NYX_BATCH_RAYS, NYX_LATE_PHASE_STEP, late_phase_trainer

from visnerf.commands import parse_fractions, positive_float
from visnerf.config import TrainConfig
from visnerf.inference import SceneRenderer, load_scene
from visnerf.training.weight_average import WeightAverage

RUN_SECONDS = 3600.0
"""The run a span is a fraction of: the hour of bench/nyx_train.py."""


def evaluate_parameters(scene: SceneRenderer, values: list[torch.Tensor], val, frames: int) -> dict:  # noqa: ANN001
    """Held-out frames rendered by ``scene``'s field with its parameters set to ``values`` (a
    fresh renderer: per-setting occupancy grids are built from the field, so none is reused)."""
    with torch.no_grad():
        for p, v in zip(scene.field.parameters(), values, strict=True):
            p.copy_(v)
    result = evaluate_frames(SceneRenderer(scene.field, scene.meta, scene.device), val, frames)
    scene.field.train()
    return result


def write_markdown(path: Path, record: dict) -> None:
    lines = markdown_header("Nyx: the parameters' moving average against their last values", record) + [
        "",
        f"Checkpoint: `{record['checkpoint']}`; stepped on for {record['train_seconds']:.0f} s of training "
        f"({record['steps']} steps of {record['batch_rays']} rays, learning rates at {record['lr_scale']:g} of "
        f"their start, averages updated every {record['every']} steps), then {record['frames']} held-out frames "
        "rendered from each set of parameters.",
        "",
        "| parameters | span (of a 60-min run) | span in seconds | PSNR | SSIM | PSNR min .. max | against the last values |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    last = record["variants"]["last"]["psnr"]
    for name, v in record["variants"].items():
        span = v.get("span")
        lines.append(f"| {name} | {fmt(span, 3) if span else '-'} | {fmt(span * RUN_SECONDS, 0) if span else '-'} | "
                     f"{fmt(v['psnr'], 3)} dB | {fmt(v['ssim'], 4)} | {fmt(v['psnr_min'], 2)} .. {fmt(v['psnr_max'], 2)} | "
                     f"{v['psnr'] - last:+.3f} dB |")
    lines.append("")
    path.write_text("\n".join(lines))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_trained_model_args(ap, "nyx_hour_r200.safetensors")
    ap.add_argument("--minutes", type=positive_float, default=12.0, help="training minutes (default 12)")
    ap.add_argument("--spans", type=parse_fractions, default=(0.01, 0.03, 0.1), metavar="F1,F2,...",
                    help="average spans, fractions of a 60-minute run (default 0.01,0.03,0.1)")
    ap.add_argument("--lr-scale", type=positive_float, default=TrainConfig.lr_decay_ratio,
                    help="learning rates as a fraction of their start (default: the schedule's end)")
    ap.add_argument("--every", type=int, default=TrainConfig.weight_average_every, help="steps between updates")
    ap.add_argument("--frames", type=int, default=24, help="held-out frames rendered (default 24)")
    ap.add_argument("--micro-batch-samples", type=int, default=TrainConfig.micro_batch_samples)
    args = ap.parse_args()
    require_checkpoint(ap, args.checkpoint)
    if not args.spans or min(args.spans) <= 0.0:
        ap.error("--spans must hold fractions above 0")
    load_before = load_average()
    train, val = nyx_split(args.data)
    scene = load_scene(Path(args.checkpoint), torch.device("cpu"))
    start = [p.detach().clone() for p in scene.field.parameters()]
    trainer = late_phase_trainer(
        train, scene.field, args.micro_batch_samples, lr_factors=TrainConfig.lr_factors * args.lr_scale,
        lr_networks=TrainConfig.lr_networks * args.lr_scale, lr_decay_ratio=1.0, **NYX_LATE_PHASE_STEP)
    averages = {span: WeightAverage.start(scene.field, span, 0.0) for span in args.spans}
    train_seconds, steps = 0.0, 0
    while train_seconds < 60.0 * args.minutes:
        t0 = time.perf_counter()
        trainer.train_step()
        train_seconds += time.perf_counter() - t0
        steps += 1
        if steps % args.every == 0:
            for avg in averages.values():
                avg.update(train_seconds / RUN_SECONDS)
    for avg in averages.values():
        avg.update(train_seconds / RUN_SECONDS)
    last = [p.detach().clone() for p in scene.field.parameters()]
    variants = {"checkpoint (before the steps)": evaluate_parameters(scene, start, val, args.frames),
                "last": evaluate_parameters(scene, last, val, args.frames)}
    for span, avg in averages.items():
        variants[f"average {span:g}"] = {"span": span, **evaluate_parameters(scene, avg.average, val, args.frames)}
    for v in variants.values():
        del v["per_frame"]
    record = {
        **machine_record(),
        "command": "python bench/nyx_weight_average.py " + " ".join(sys.argv[1:]),
        "load_average_1min": {"before": load_before, "after": load_average()},
        "checkpoint": args.checkpoint, "train_seconds": round(train_seconds, 1), "steps": steps,
        "batch_rays": NYX_BATCH_RAYS, "lr_scale": args.lr_scale, "every": args.every, "frames": args.frames,
        "variants": variants,
    }
    write_results(Path(args.results), "nyx_weight_average", record, write_markdown)
    for name, v in variants.items():
        print(f"{name}: {v['psnr']:.3f} dB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
