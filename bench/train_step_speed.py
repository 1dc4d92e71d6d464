"""Time of one Nyx training step: the VM lookups' backward, glibc's handling of freed blocks and
the micro-batch size.

Three backwards of the lookups' table gradient:

- ``embedding_bag``: its own CPU backward (sorts the taps, adds one row per tap);
- ``transposed product``: the compressed-row tap matrix transposed at every call, times the
  incoming gradient; autograd allocates each micro-batch's table-sized gradient and adds it into
  ``.grad`` (what the lookups did before the in-place product);
- ``in-place product``: ``vm_taps.weighted_row_sum`` as it is: ``T^T`` built from a stable sort and
  added into ``.grad`` in place inside the trainer's ``table_gradients_in_place``.

Two allocators: glibc's defaults and ``runtime.keep_freed_blocks`` (blocks up to 32 MiB kept in
the heap once freed, so table-sized tensors do not fault their pages in at every use). And the
trainer's ``micro_batch_samples``.

Part 1 times the lookup alone on tables of a 170^3 model (the appearance and density plane and
line tables) with Nyx-sized micro-batches, accumulating into ``.grad`` as a trainer does. Part 2
runs ``Trainer.train_step`` on Nyx from a trained checkpoint (the state most of a run is spent
in: the final grid, an occupancy mask), each combination in its own process (mallopt is
process-wide), alternating over ``--rounds``: seconds per step (median over the steps), minor
page faults and system time per step, peak RSS.

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
import warnings
from collections.abc import Callable
from itertools import product
from pathlib import Path

import torch
import torch.nn.functional as F
from bench_common import (
    RESULTS,
    ROOT,
    load_average,
    machine_record,
    markdown_header,
    nyx_split,
    require_checkpoint,
    write_results,
)
from nyx_train import late_phase_trainer

BACKWARDS = ("embedding_bag", "transposed product", "in-place product")
ALLOCATORS = ("glibc default", "keep freed blocks")
LOOKUPS = (("appearance plane", 86700, 48, 4), ("density plane", 86700, 16, 4),
           ("appearance line", 510, 48, 2), ("density line", 510, 16, 2))
"""(table, rows, channels, taps per bag) of a 170^3 model; 74000 bags (3 modes of ~24700 samples)."""


def embedding_bag_sum(rows: torch.Tensor, weights: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """``vm_taps.weighted_row_sum`` with ``embedding_bag``'s own backward."""
    return F.embedding_bag(rows, table, per_sample_weights=weights, mode="sum")


class _TransposedProduct(torch.autograd.Function):
    """The lookups' backward before the in-place product: ``T`` in compressed-row form (row ``i``
    holds its ``k`` taps), transposed at the product, a fresh gradient per call."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, rows: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:  # noqa: ANN001
        ctx.save_for_backward(rows, weights)
        ctx.n_rows = table.shape[0]
        return F.embedding_bag(rows, table, per_sample_weights=weights, mode="sum")

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None, None]:  # noqa: ANN001
        rows, weights = ctx.saved_tensors
        m, k = rows.shape
        crow = torch.arange(0, m * k + 1, k, dtype=rows.dtype)
        with warnings.catch_warnings():  # "sparse CSR support is in beta"
            warnings.simplefilter("ignore", UserWarning)
            taps = torch.sparse_csr_tensor(crow, rows.reshape(-1), weights.reshape(-1).to(grad.dtype),
                                           size=(m, ctx.n_rows), check_invariants=False)
            return taps.t() @ grad.contiguous(), None, None


def transposed_product_sum(rows: torch.Tensor, weights: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """``vm_taps.weighted_row_sum`` with the transposed-product backward."""
    return _TransposedProduct.apply(table, rows, weights)


def lookup_of(backward: str) -> Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]:
    from visnerf.representation.vm_taps import weighted_row_sum

    return {"embedding_bag": embedding_bag_sum, "transposed product": transposed_product_sum,
            "in-place product": weighted_row_sum}[backward]


def time_lookups(bags: int, repeats: int) -> list[dict]:
    """Forward and backward of each table's lookup, each backward, interleaved, each adding into a
    ``.grad`` that is already there (as the micro-batches of a step do); medians in ms."""
    from visnerf.representation.vm_taps import table_gradients_in_place

    g = torch.Generator().manual_seed(0)
    rows_out = []
    for name, n_rows, channels, taps in LOOKUPS:
        rows = torch.randint(0, n_rows, (bags, taps), generator=g, dtype=torch.int32)
        weights = torch.rand(bags, taps, generator=g)
        cotangent = torch.randn(bags, channels, generator=g)
        table = torch.randn(n_rows, channels, generator=g).requires_grad_(True)
        table.grad = torch.zeros_like(table)
        times: dict[str, list[float]] = {k: [] for k in BACKWARDS}
        for rep in range(repeats + 1):
            for way in BACKWARDS:
                t0 = time.perf_counter()
                with table_gradients_in_place():
                    lookup_of(way)(rows, weights, table).backward(cotangent)
                if rep:  # the first round warms up
                    times[way].append(1000 * (time.perf_counter() - t0))
        rows_out.append({"table": name, "rows": n_rows, "channels": channels, "taps": taps, "bags": bags,
                         **{f"{k}_ms": statistics.median(v) for k, v in times.items()}})
    return rows_out


def measure_step(backward: str, allocator: str, micro_batch_samples: int, checkpoint: Path, data: Path,
                 steps: int, threads: int) -> dict:
    """In this process: ``steps`` training steps from ``checkpoint`` with one combination."""
    import visnerf.representation.vm_taps as vm_taps
    import visnerf.training.trainer as trainer_module
    from visnerf.checkpoint import load_checkpoint
    from visnerf.config import TrainConfig
    from visnerf.runtime import release_free_memory

    torch.set_num_threads(threads)
    vm_taps.weighted_row_sum = lookup_of(backward)  # lookup_modes reads the module's name at each call
    if allocator == "glibc default":
        trainer_module.keep_freed_blocks = lambda: False
    train, _ = nyx_split(data)
    field_, _ = load_checkpoint(checkpoint, torch.device("cpu"))
    trainer = late_phase_trainer(train, field_, micro_batch_samples)  # Trainer reads the patched allocator setting
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
        "backward": backward, "allocator": allocator, "micro_batch_samples": micro_batch_samples, "steps": steps,
        "samples_per_step": samples, "step_seconds_median": statistics.median(seconds),
        "page_faults_per_step": (usage1.ru_minflt - usage0.ru_minflt) / steps,
        "system_seconds_per_step": (usage1.ru_stime - usage0.ru_stime) / steps,
        "peak_rss_mb": usage1.ru_maxrss / 1024.0,
    }  # fmt: skip


def config_name(backward: str, allocator: str, micro_batch_samples: int) -> str:
    return f"{backward}, {allocator}, {micro_batch_samples} samples"


def write_markdown(path: Path, record: dict) -> None:
    lines = [
        *markdown_header("Training step time: the lookups' backward, the allocator, the micro-batch size", record),
        "",
        f"## The lookup alone ({record['lookup_bags']} bags, median of {record['lookup_repeats']}, forward and "
        "backward into an existing `.grad`)",
        "",
        "| table | rows x channels | taps per bag | " + " | ".join(BACKWARDS) + " |",
        "| --- | --- | --- | " + " | ".join("---" for _ in BACKWARDS) + " |",
    ]
    for r in record["lookups"]:
        lines.append(f"| {r['table']} | {r['rows']} x {r['channels']} | {r['taps']} | "
                     + " | ".join(f"{r[k + '_ms']:.1f} ms" for k in BACKWARDS) + " |")
    lines += [
        "",
        f"## One Nyx training step from `{record['checkpoint']}` ({record['steps']} steps per process, "
        f"{record['rounds']} rounds, alternating)",
        "",
        "| backward | allocator | micro-batch samples | round | s per step (median) | page faults per step | "
        "system s per step | peak RSS | samples per step |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in record["steps_rows"]:
        lines.append(f"| {r['backward']} | {r['allocator']} | {r['micro_batch_samples']} | {r['round']} | "
                     f"{r['step_seconds_median']:.3f} | {r['page_faults_per_step']:.0f} | "
                     f"{r['system_seconds_per_step']:.3f} | {r['peak_rss_mb']:.0f} MB | {r['samples_per_step']:.0f} |")
    s = record["summary"]
    first = next(iter(s.values()))
    lines += ["", "Median over the rounds, seconds per step:", ""]
    lines += [f"- {k}: {v:.3f} s ({first / v:.2f}x the first)" for k, v in s.items()]
    lines.append("")
    path.write_text("\n".join(lines))


def name_list(text: str, allowed: tuple[str, ...], flag: str) -> tuple[str, ...]:
    names = tuple(x.strip() for x in text.split(",") if x.strip())
    unknown = [x for x in names if x not in allowed]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"{flag}: unknown {unknown or 'nothing given'}; choose from {', '.join(allowed)}")
    return names


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, default=ROOT / "runs" / "nyx_final_grid.safetensors",
                        help="a trained Nyx checkpoint (bench/nyx_train.py writes one)")
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "nyx")
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--backwards", type=lambda t: name_list(t, BACKWARDS, "--backwards"), default=BACKWARDS,
                        help=f"comma-separated, of {', '.join(BACKWARDS)} (default all)")
    parser.add_argument("--allocators", type=lambda t: name_list(t, ALLOCATORS, "--allocators"),
                        default=("keep freed blocks",), help=f"comma-separated, of {', '.join(ALLOCATORS)} "
                        "(default keep freed blocks, as the trainer)")
    parser.add_argument("--micro-batch-samples", type=lambda t: tuple(int(x) for x in t.split(",")), default=(32768,),
                        help="comma-separated TrainConfig.micro_batch_samples values (default 32768)")
    parser.add_argument("--lookup-bags", type=int, default=74000)
    parser.add_argument("--lookup-repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--one", nargs=3, help=argparse.SUPPRESS)  # child: measure this combination
    parser.add_argument("--out-dir", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.one is not None:
        backward, allocator, samples = args.one
        print(json.dumps(measure_step(backward, allocator, int(samples), args.checkpoint, args.data, args.steps,
                                      args.threads)))
        return 0
    require_checkpoint(parser, args.checkpoint)
    if min(args.steps, args.rounds, args.lookup_bags, args.lookup_repeats, args.threads, *args.micro_batch_samples) < 1:
        parser.error("--steps, --rounds, --micro-batch-samples, --lookup-bags, --lookup-repeats and --threads "
                     "must be positive")
    configs = list(product(args.backwards, args.allocators, args.micro_batch_samples))
    load_before = load_average()
    torch.set_num_threads(args.threads)
    lookups = time_lookups(args.lookup_bags, args.lookup_repeats)
    for r in lookups:
        print(f"{r['table']}: " + ", ".join(f"{k} {r[k + '_ms']:.1f} ms" for k in BACKWARDS), file=sys.stderr)
    rows = []
    for round_ in range(1, args.rounds + 1):
        for backward, allocator, samples in configs:
            child = [sys.executable, __file__, "--one", backward, allocator, str(samples), "--checkpoint",
                     str(args.checkpoint), "--data", str(args.data), "--steps", str(args.steps), "--threads",
                     str(args.threads)]
            result = subprocess.run(child, check=True, capture_output=True, text=True)
            rows.append({**json.loads(result.stdout.strip().splitlines()[-1]), "round": round_})
            print(f"round {round_}, {config_name(backward, allocator, samples)}: "
                  f"{rows[-1]['step_seconds_median']:.3f} s per step, {rows[-1]['page_faults_per_step']:.0f} faults",
                  file=sys.stderr)
    summary = {config_name(*c): statistics.median(r["step_seconds_median"] for r in rows
                                                  if (r["backward"], r["allocator"], r["micro_batch_samples"]) == c)
               for c in configs}
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
