"""Time of one Nyx training step: the VM lookups' backward and glibc's handling of freed blocks.

Two changes, measured side by side in one run:

- **backward**: ``embedding_bag``'s own CPU backward (sorts the taps, adds one row per tap) against
  ``vm_taps.weighted_row_sum`` (the tap matrix in compressed-row form, one sparse-dense product);
- **allocator**: glibc's defaults against ``runtime.keep_freed_blocks`` (blocks up to 32 MiB kept
  in the heap once freed, so table-sized tensors do not fault their pages in at every use).

Part 1 times the lookup alone on tables of a 170^3 model (the appearance and density plane and
line tables) with Nyx-sized micro-batches. Part 2 runs ``Trainer.train_step`` on Nyx from a
trained checkpoint (the state most of a run is spent in: the final grid, an occupancy mask), each
of the four combinations in its own process (mallopt is process-wide), alternating over
``--rounds``: seconds per step (median over the steps), minor page faults and system time per
step, peak RSS.

    python bench/train_step_speed.py --checkpoint runs/nyx_final_grid.safetensors

Writes bench/results/train_step_speed.{json,md}.
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
import torch.nn.functional as F
from bench_common import RESULTS, ROOT, holdout_for, load_average, machine_record, markdown_header, write_results
from nyx_train import NYX_STEP_RATIO

CONFIGS = (("embedding_bag", "glibc default"), ("sparse product", "glibc default"),
           ("embedding_bag", "keep freed blocks"), ("sparse product", "keep freed blocks"))
LOOKUPS = (("appearance plane", 86700, 48, 4), ("density plane", 86700, 16, 4),
           ("appearance line", 510, 48, 2), ("density line", 510, 16, 2))
"""(table, rows, channels, taps per bag) of a 170^3 model; 74000 bags (3 modes of ~24700 samples)."""


def embedding_bag_sum(rows: torch.Tensor, weights: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """``vm_taps.weighted_row_sum`` with ``embedding_bag``'s own backward (what it replaced)."""
    return F.embedding_bag(rows, table, per_sample_weights=weights, mode="sum")


def time_lookups(bags: int, repeats: int) -> list[dict]:
    """Forward and backward of each table's lookup, both ways, interleaved; medians in ms."""
    from visnerf.representation.vm_taps import weighted_row_sum

    g = torch.Generator().manual_seed(0)
    rows_out = []
    for name, n_rows, channels, taps in LOOKUPS:
        rows = torch.randint(0, n_rows, (bags, taps), generator=g, dtype=torch.int32)
        weights = torch.rand(bags, taps, generator=g)
        cotangent = torch.randn(bags, channels, generator=g)
        table = torch.randn(n_rows, channels, generator=g).requires_grad_(True)
        ways = {"embedding_bag": embedding_bag_sum, "sparse product": weighted_row_sum}
        times: dict[str, list[float]] = {k: [] for k in ways}
        for rep in range(repeats + 1):
            for way, lookup in ways.items():
                table.grad = None
                t0 = time.perf_counter()
                lookup(rows, weights, table).backward(cotangent)
                if rep:  # the first round warms up
                    times[way].append(1000 * (time.perf_counter() - t0))
        rows_out.append({"table": name, "rows": n_rows, "channels": channels, "taps": taps, "bags": bags,
                         **{f"{k}_ms": statistics.median(v) for k, v in times.items()}})
    return rows_out


def measure_step(backward: str, allocator: str, checkpoint: Path, data: Path, steps: int, threads: int) -> dict:
    """In this process: ``steps`` training steps from ``checkpoint`` with one combination."""
    import visnerf.representation.vm_taps as vm_taps
    import visnerf.training.trainer as trainer_module
    from visnerf.checkpoint import load_checkpoint
    from visnerf.config import RenderConfig, TrainConfig
    from visnerf.data.holdout import split_holdout
    from visnerf.data.parsers.blender import load_dataset
    from visnerf.runtime import release_free_memory

    torch.set_num_threads(threads)
    if backward == "embedding_bag":
        vm_taps.weighted_row_sum = embedding_bag_sum
    if allocator == "glibc default":
        trainer_module.keep_freed_blocks = lambda: False
    scene = load_dataset(data)
    train, _ = split_holdout(scene, holdout_for(scene))
    del scene
    field_, _ = load_checkpoint(checkpoint, torch.device("cpu"))
    res = field_.resolution[0]
    cfg = TrainConfig(iterations=10**9, resolution_init=res, resolution_final=res, upsample_at=(), occupancy_at=(),
                      trim_every=10**9)
    trainer = trainer_module.Trainer(train, None, cfg, torch.device("cpu"), render_cfg=RenderConfig(step_ratio=NYX_STEP_RATIO),
                                     init_field=field_)
    for _ in range(3):
        trainer.train_step()
    usage0 = resource.getrusage(resource.RUSAGE_SELF)
    seconds, samples = [], 0.0
    for i in range(steps):
        t0 = time.perf_counter()
        samples = trainer.train_step()["samples"]
        seconds.append(time.perf_counter() - t0)
        if (i + 1) % TrainConfig.trim_every == 0:  # as Trainer.run does, between steps (untimed)
            release_free_memory()
    usage1 = resource.getrusage(resource.RUSAGE_SELF)
    return {
        "backward": backward, "allocator": allocator, "steps": steps, "samples_per_step": samples,
        "step_seconds_median": statistics.median(seconds),
        "page_faults_per_step": (usage1.ru_minflt - usage0.ru_minflt) / steps,
        "system_seconds_per_step": (usage1.ru_stime - usage0.ru_stime) / steps,
        "peak_rss_mb": usage1.ru_maxrss / 1024.0,
    }  # fmt: skip


def write_markdown(path: Path, record: dict) -> None:
    lines = [
        *markdown_header("Training step time: the lookups' backward and the allocator", record),
        "",
        f"## The lookup alone ({record['lookup_bags']} bags, median of {record['lookup_repeats']}, forward and backward)",
        "",
        "| table | rows x channels | taps per bag | embedding_bag | sparse product | ratio |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for r in record["lookups"]:
        lines.append(f"| {r['table']} | {r['rows']} x {r['channels']} | {r['taps']} | {r['embedding_bag_ms']:.1f} ms | "
                     f"{r['sparse product_ms']:.1f} ms | {r['embedding_bag_ms'] / r['sparse product_ms']:.2f}x |")
    lines += [
        "",
        f"## One Nyx training step from `{record['checkpoint']}` ({record['steps']} steps per process, "
        f"{record['rounds']} rounds, alternating)",
        "",
        "| backward | allocator | round | s per step (median) | page faults per step | system s per step | "
        "peak RSS | samples per step |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in record["steps_rows"]:
        lines.append(f"| {r['backward']} | {r['allocator']} | {r['round']} | {r['step_seconds_median']:.3f} | "
                     f"{r['page_faults_per_step']:.0f} | {r['system_seconds_per_step']:.3f} | {r['peak_rss_mb']:.0f} MB | "
                     f"{r['samples_per_step']:.0f} |")
    s = record["summary"]
    lines += ["", "Median over the rounds, seconds per step:", ""]
    lines += [f"- {k}: {v:.3f} s ({s[CONFIGS[0][0] + ', ' + CONFIGS[0][1]] / v:.2f}x the first)" for k, v in s.items()]
    lines.append("")
    path.write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, default=ROOT / "runs" / "nyx_final_grid.safetensors",
                        help="a trained Nyx checkpoint (bench/nyx_train.py writes one)")
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "nyx")
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--lookup-bags", type=int, default=74000)
    parser.add_argument("--lookup-repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--one", nargs=2, help=argparse.SUPPRESS)  # child: measure this combination
    parser.add_argument("--out-dir", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.one is not None:
        print(json.dumps(measure_step(*args.one, args.checkpoint, args.data, args.steps, args.threads)))
        return 0
    if not args.checkpoint.is_file():
        parser.error(f"{args.checkpoint} does not exist: train one with bench/nyx_train.py, or pass --checkpoint")
    if min(args.steps, args.rounds, args.lookup_bags, args.lookup_repeats, args.threads) < 1:
        parser.error("--steps, --rounds, --lookup-bags, --lookup-repeats and --threads must be positive")
    load_before = load_average()
    torch.set_num_threads(args.threads)
    lookups = time_lookups(args.lookup_bags, args.lookup_repeats)
    for r in lookups:
        print(f"{r['table']}: embedding_bag {r['embedding_bag_ms']:.1f} ms, sparse product {r['sparse product_ms']:.1f} ms",
              file=sys.stderr)
    rows = []
    for round_ in range(1, args.rounds + 1):
        for backward, allocator in CONFIGS:
            child = [sys.executable, __file__, "--one", backward, allocator, "--checkpoint", str(args.checkpoint),
                     "--data", str(args.data), "--steps", str(args.steps), "--threads", str(args.threads)]
            result = subprocess.run(child, check=True, capture_output=True, text=True)
            rows.append({**json.loads(result.stdout.strip().splitlines()[-1]), "round": round_})
            print(f"round {round_}, {backward}, {allocator}: {rows[-1]['step_seconds_median']:.3f} s per step, "
                  f"{rows[-1]['page_faults_per_step']:.0f} faults", file=sys.stderr)
    summary = {f"{b}, {a}": statistics.median(r["step_seconds_median"] for r in rows
                                              if (r["backward"], r["allocator"]) == (b, a)) for b, a in CONFIGS}
    record = {
        **machine_record(), "command": "python bench/train_step_speed.py " + " ".join(argv or sys.argv[1:]),
        "torch_threads": args.threads, "checkpoint": str(args.checkpoint.relative_to(ROOT)
                                                         if args.checkpoint.is_relative_to(ROOT) else args.checkpoint),
        "steps": args.steps, "rounds": args.rounds, "lookup_bags": args.lookup_bags,
        "lookup_repeats": args.lookup_repeats, "load_average_1min": {"before": load_before, "after": load_average()},
        "lookups": lookups, "steps_rows": rows, "summary": summary,
    }  # fmt: skip
    write_results(args.out_dir, "train_step_speed", record, write_markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
