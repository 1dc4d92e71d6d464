"""What torch's fused Adam buys on this CPU: the optimizer step alone and whole Nyx training steps.

``trainer.make_optimizer`` builds a fused Adam on the CPU and CUDA (``FUSED_ADAM_DEVICES``): one
pass over each parameter tensor instead of the default implementation's chain of about ten
elementwise kernels (``lerp_``, ``mul_``, ``addcmul_``, ``sqrt``, ``div``, ``addcdiv_``, ...).
From a trained checkpoint, one trainer steps the field as the late phase of a run does
(``nyx_train.late_phase_trainer``) with two optimizers over the same parameters, one fused and
one the default way, swapped in turn:

- the optimizer step alone, on the gradients a real training step left, ``--rounds`` x ``--steps``;
- whole training steps with each optimizer, alternating over ``--rounds``;
- the update itself: from one state and one set of gradients, the largest difference between
  the parameters after a fused and after a default step (the same algorithm, so rounding only).

    python bench/optimizer_speed.py --checkpoint runs/nyx.safetensors

Writes bench/results/optimizer_speed.{json,md}.
"""

import argparse
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
    require_checkpoint,
    step_time_summary,
    write_results,
)
from nyx_train import NYX_BATCH_RAYS, late_phase_trainer

from visnerf.checkpoint import load_checkpoint
from visnerf.training.trainer import Trainer

KINDS = ("fused", "default")


def adam_like(optimizer: torch.optim.Adam, fused: bool) -> torch.optim.Adam:
    """A fresh Adam over ``optimizer``'s parameter groups with their rates, fused or the default way."""
    groups = [{"params": g["params"], "lr": g["lr"], "base_lr": g["base_lr"]} for g in optimizer.param_groups]
    return torch.optim.Adam(groups, betas=optimizer.defaults["betas"], fused=fused, foreach=None if fused else False)


def update_difference(trainer: Trainer) -> float:
    """Largest |fused - default| over the parameters after one step of each from the same state."""
    params = [p for g in trainer.optimizer.param_groups for p in g["params"]]
    start = [p.detach().clone() for p in params]
    results = []
    for fused in (True, False):
        with torch.no_grad():
            for p, s in zip(params, start, strict=True):
                p.copy_(s)
        adam_like(trainer.optimizer, fused).step()
        results.append([p.detach().clone() for p in params])
    with torch.no_grad():
        for p, s in zip(params, start, strict=True):
            p.copy_(s)
    return max(float((a - b).abs().max()) for a, b in zip(*results, strict=True))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_trained_model_args(ap, "nyx.safetensors")
    add_step_timing_args(ap, steps=6, per="optimizer")
    args = ap.parse_args()
    if min(args.rounds, args.steps) < 1:
        ap.error("--rounds and --steps must be at least 1")
    require_checkpoint(ap, args.checkpoint)
    load_before = load_average()
    train, _ = nyx_split(args.data)
    field, _ = load_checkpoint(args.checkpoint, torch.device("cpu"))
    trainer = late_phase_trainer(train, field, args.micro_batch_samples, batch_rays=NYX_BATCH_RAYS)
    trainer.train_step()  # warm-up, and gradients for the update check and the step-alone timing
    difference = update_difference(trainer)
    optimizers = {kind: adam_like(trainer.optimizer, kind == "fused") for kind in KINDS}
    alone: dict[str, list[float]] = {kind: [] for kind in KINDS}
    for _ in range(args.rounds):
        for kind, optimizer in optimizers.items():
            for _ in range(args.steps):
                t0 = time.perf_counter()
                optimizer.step()
                alone[kind].append(1000 * (time.perf_counter() - t0))
    def use_optimizer(kind: str) -> None:  # the shared trainer steps with one of the two (an assignment)
        trainer.optimizer = optimizers[kind]

    step_ms, _ = alternate_steps(dict.fromkeys(KINDS, trainer), args.rounds, args.steps, before_step=use_optimizer,
                                 warm_up=True)
    record: dict[str, Any] = {
        **machine_record(),
        "command": " ".join(["python bench/optimizer_speed.py", *sys.argv[1:]]),
        "load_average_1min": {"before": load_before, "after": load_average()},
        "checkpoint": args.checkpoint, "resolution": list(field.resolution),
        "parameters": sum(p.numel() for p in field.parameters()),
        "batch_rays": trainer.cfg.batch_rays, "rounds": args.rounds, "steps_per_round": args.steps,
        "optimizer_step": {kind: step_time_summary(ms) for kind, ms in alone.items()},
        "training_step": {kind: step_time_summary(ms) for kind, ms in step_ms.items()},
        "max_update_difference": difference,
    }
    write_results(Path(args.results), "optimizer_speed", record, write_markdown)
    for part in ("optimizer_step", "training_step"):
        print(part, {k: round(v["median_ms"], 1) for k, v in record[part].items()})
    return 0


def write_markdown(path: Path, record: dict[str, Any]) -> None:
    def table(part: str) -> list[str]:
        rows = record[part]
        return ["| Adam | median ms | min | max |", "| --- | --- | --- | --- |",
                *(f"| {kind} | {r['median_ms']:.1f} | {r['min_ms']:.1f} | {r['max_ms']:.1f} |" for kind, r in rows.items()),
                "", f"default / fused (medians): {rows['default']['median_ms'] / rows['fused']['median_ms']:.2f}x.", ""]

    lines = [
        *markdown_header("Fused or default Adam: the optimizer step and Nyx training steps", record),
        f"Checkpoint: `{record['checkpoint']}` (grid {record['resolution']}, {record['parameters']} parameters), "
        f"{record['batch_rays']} rays per training step, {record['rounds']} rounds of {record['steps_per_round']} "
        "steps each way, alternating.",
        "",
        "The optimizer step alone (on one training step's gradients):",
        "",
        *table("optimizer_step"),
        "Whole training steps:",
        "",
        *table("training_step"),
        f"One step of each from the same state and gradients: the parameters differ by at most "
        f"{record['max_update_difference']:.3g}.",
        "",
    ]
    path.write_text("\n".join(lines))


if __name__ == "__main__":
    sys.exit(main())
