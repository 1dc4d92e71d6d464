"""Peak memory and time of one training step against the micro-batch sample budget.

A training step renders and back-propagates its 4096 rays in micro-batches of at most
``TrainConfig.micro_batch_samples`` evaluated samples (``trainer.micro_batches``), so activation memory is
bounded by that budget, not by the batch. This measures, for each budget, one full step (every
micro-batch forward and backward, as ``Trainer.train_step`` does) on a field the size of the Nyx
model at its finest grid (88x140x140 in the carved box, K = 3) in the state that costs most: a
fresh field's faint fog, where every sample's colour is decoded. Each budget runs in its own
process, so each peak RSS is its own; the step is repeated and the median time kept.

    python bench/train_step_memory.py --threads 1

Writes bench/results/train_step_memory.{json,md}.
"""

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch
from bench_common import RESULTS, load_average, machine_record, markdown_header, write_results

from visnerf.config import FieldConfig, TrainConfig
from visnerf.rendering.renderer import place_samples, shade_rays
from visnerf.representation.field import VisNerfField
from visnerf.training.trainer import micro_batches, set_mixed_precision

RESOLUTION = (88, 140, 140)  # bench/results/nyx_train.json: the finest grid in the carved box
BOX = ((-0.11, -0.18, -0.18), (0.11, 0.18, 0.18))


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def measure(budget: int, batch_rays: int, repeats: int, threads: int) -> dict:
    """One budget, in this process: peak RSS before and after the steps, and the step times."""
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    field_ = VisNerfField(FieldConfig(resolution=RESOLUTION, param_lengths=(5, 5, 5)), torch.tensor(BOX))
    set_mixed_precision(field_, True)
    # Rays from a sphere around the box towards points near its centre: every ray crosses it.
    origins = torch.randn(batch_rays, 3)
    origins = origins / origins.norm(dim=-1, keepdim=True)
    directions = torch.randn(batch_rays, 3) * 0.05 - origins
    directions = directions / directions.norm(dim=-1, keepdim=True)
    params = torch.rand(batch_rays, 3) * 2 - 1
    background = torch.ones(batch_rays, 3)
    target = torch.full((batch_rays, 3), 0.5)
    step = field_.voxel_size() * 0.5
    before = peak_rss_mb()
    seconds, samples = [], 0
    for _ in range(repeats):
        field_.zero_grad(set_to_none=True)
        t0 = time.perf_counter()
        placed = place_samples(field_, origins, directions, params, step, 1024, None)
        slices = micro_batches(placed.per_ray(), TrainConfig.micro_batch_rays, budget)
        samples = 0
        for sl in slices:
            out = shade_rays(field_, directions[sl], params[sl], background[sl], placed.of_rays(sl))
            (((out["rgb"] - target[sl]) ** 2).sum() / (3 * batch_rays)).backward()
            samples += int(out["n_samples"])
        seconds.append(time.perf_counter() - t0)
    return {
        "micro_batch_samples": budget, "micro_batches": len(slices), "samples_per_step": samples,
        "peak_rss_before_mb": round(before), "peak_rss_mb": round(peak_rss_mb()),
        "step_seconds_median": statistics.median(seconds), "step_seconds": seconds,
    }  # fmt: skip


def write_markdown(path: Path, record: dict) -> None:
    lines = [
        *markdown_header("Training step memory against the micro-batch sample budget", record),
        "",
        f"One step of {record['batch_rays']} rays on a field of {'x'.join(map(str, RESOLUTION))} voxels, K = 3, "
        "in a fresh field's fog (every sample's colour decoded); each budget in its own process, "
        f"median of {record['repeats']} steps.",
        "",
        "| samples per micro-batch | micro-batches | samples per step | peak RSS | above the process before the step | "
        "step time |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for r in record["rows"]:
        lines.append(
            f"| {r['micro_batch_samples']} | {r['micro_batches']} | {r['samples_per_step']} | {r['peak_rss_mb']} MB | "
            f"+{r['peak_rss_mb'] - r['peak_rss_before_mb']} MB | {r['step_seconds_median']:.2f} s |"
        )
    lines += ["", f"Default: `TrainConfig.micro_batch_samples = {TrainConfig.micro_batch_samples}`.", ""]
    path.write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--budgets", type=int, nargs="+", default=[131072, 65536, 32768])
    parser.add_argument("--batch-rays", type=int, default=TrainConfig.batch_rays)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # child process: measure this budget
    parser.add_argument("--out-dir", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.one is not None:
        print(json.dumps(measure(args.one, args.batch_rays, args.repeats, args.threads)))
        return 0
    if min(args.budgets) < 1 or args.batch_rays < 1 or args.repeats < 1:
        parser.error("--budgets, --batch-rays and --repeats must be positive")
    load_before = load_average()
    rows = []
    for budget in args.budgets:
        child = [sys.executable, __file__, "--one", str(budget), "--batch-rays", str(args.batch_rays),
                 "--repeats", str(args.repeats), "--threads", str(args.threads)]  # fmt: skip
        result = subprocess.run(child, check=True, capture_output=True, text=True)
        rows.append(json.loads(result.stdout.strip().splitlines()[-1]))
        print(f"budget {budget}: peak RSS {rows[-1]['peak_rss_mb']} MB, "
              f"step {rows[-1]['step_seconds_median']:.2f} s", file=sys.stderr)  # fmt: skip
    record = {
        **machine_record(), "command": "python bench/train_step_memory.py " + " ".join(argv or sys.argv[1:]),
        "torch_threads": args.threads, "batch_rays": args.batch_rays, "repeats": args.repeats,
        "load_average_1min": {"before": load_before, "after": load_average()}, "rows": rows,
    }  # fmt: skip
    write_results(args.out_dir, "train_step_memory", record, write_markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
