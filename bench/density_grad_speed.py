"""Time of a Nyx training step with sampled density gradients (``TrainConfig.density_grad_keep``).

From a trained checkpoint (the state most of a run is spent in), one trainer per keep fraction
steps the same field in turn, alternating over ``--rounds`` (each trainer its own optimizer), so
the fractions share the machine's noise. Also counts, over the measured steps, the density
samples a step evaluates, the share of them below the near-empty floor, and how many the backward
pass takes.

    python bench/density_grad_speed.py --checkpoint runs/nyx_refine.safetensors

Writes bench/results/density_grad_speed.{json,md}.
"""

import argparse
import sys
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
from nyx_train import late_phase_trainer

from visnerf.checkpoint import load_checkpoint
from visnerf.config import TrainConfig


class SampleCounter:
    """Counts a step's density samples by wrapping ``field.density``: with sampled gradients the
    step evaluates every sample without a graph, then the traced ones with one; without, every
    sample once, with a graph."""

    def __init__(self, field: torch.nn.Module, step: float, floor: float) -> None:
        self.real, self.step, self.floor = field.density, step, floor
        self.calls: list[tuple[bool, int, int]] = []  # (with a graph, samples, near-empty samples)

    def __call__(self, points: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        out = self.real(points, q)
        near_empty = int((-torch.expm1(-out.detach() * self.step) < self.floor).sum())
        self.calls.append((torch.is_grad_enabled(), out.shape[0], near_empty))
        return out

    def take(self) -> tuple[int, int, int]:
        """(evaluated, near-empty, back-propagated) samples since the last call."""
        plain = [c for c in self.calls if not c[0]]
        traced = sum(c[1] for c in self.calls if c[0])
        first = plain or [c for c in self.calls if c[0]]
        self.calls = []
        return sum(c[1] for c in first), sum(c[2] for c in first), traced


def write_markdown(path: Path, record: dict[str, Any]) -> None:
    lines = [*markdown_header("Sampled density gradients: seconds per Nyx training step", record),
             f"Checkpoint: `{record['checkpoint']}` (grid {record['resolution']}), {record['rounds']} rounds of "
             f"{record['steps']} steps per fraction, alternating.", "",
             "| keep | median ms per step | min | max | speed-up (medians) | density samples per step | near-empty "
             "| back-propagated |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    base = record["results"][0]["median_ms"]
    for row in record["results"]:
        lines.append(f"| {row['keep']:g} | {row['median_ms']:.1f} | {row['min_ms']:.1f} | {row['max_ms']:.1f} | "
                     f"{base / row['median_ms']:.2f}x | {row['density_samples']:.0f} | "
                     f"{100 * row['near_empty_share']:.1f} % | {100 * row['traced_share']:.1f} % |")
    lines.append("")
    path.write_text("\n".join(lines))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_trained_model_args(ap, "nyx_refine.safetensors")
    add_step_timing_args(ap, steps=3, per="fraction")
    ap.add_argument("--keep", default="1,0.25,0.125,0.0625", help="fractions to time, the first being 1")
    args = ap.parse_args()
    keeps = [float(k) for k in args.keep.split(",")]
    if keeps[0] != 1.0 or not all(0.0 < k <= 1.0 for k in keeps):
        ap.error("--keep: fractions in (0, 1], the first one 1")
    load_before = load_average()
    train, _ = nyx_split(args.data)
    field, _ = load_checkpoint(args.checkpoint, torch.device("cpu"))
    trainers = {}
    for keep in keeps:
        trainers[keep] = late_phase_trainer(train, field, args.micro_batch_samples, density_grad_keep=keep)
        trainers[keep].train_step()  # warm-up
    counter = SampleCounter(field, trainers[1.0].step_size(), TrainConfig.density_grad_floor)
    field.density = counter  # the renderer calls the instance's attribute
    counts: dict[float, list[tuple[int, int, int]]] = {k: [] for k in keeps}
    times, _ = alternate_steps(trainers, args.rounds, args.steps, lambda keep: counts[keep].append(counter.take()))
    results = []
    for keep in keeps:
        evaluated = sum(c[0] for c in counts[keep])
        results.append({"keep": keep, **step_time_summary(times[keep]), "density_samples": evaluated / len(counts[keep]),
                        "near_empty_share": sum(c[1] for c in counts[keep]) / max(1, evaluated),
                        "traced_share": sum(c[2] for c in counts[keep]) / max(1, evaluated)})
    record = {
        **machine_record(),
        "command": " ".join(["python bench/density_grad_speed.py", *sys.argv[1:]]),
        "load_average_1min": {"before": load_before, "after": load_average()},
        "checkpoint": args.checkpoint, "resolution": list(field.resolution),
        "rounds": args.rounds, "steps": args.steps, "results": results,
    }
    write_results(Path(args.results), "density_grad_speed", record, write_markdown)
    for row in results:
        print(f"keep {row['keep']:g}: {row['median_ms']:.1f} ms, back-propagated {100 * row['traced_share']:.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
