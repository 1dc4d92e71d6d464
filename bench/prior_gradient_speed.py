"""Time of the priors' gradient on a Nyx-sized field: autograd against the in-place gradients.

The trainer's priors (L1 on the density factors, total variation on the appearance factors and
the parameter vectors, L1 pull of the parameter vectors toward 1) on a field of the Nyx recipe's
size (170^3, 16 + 48 components, three parameter axes of 3, 3 and 5 values):

- ``autograd``: ``sum(regularization(field, w).values()).backward()``, as the trainer did;
- ``in place``: ``backward_regularization(field, w)``, as it does now.

Each round times both, alternating, ``--repeats`` times each, with ``.grad`` set to None before
each call as the trainer's ``zero_grad`` does; medians in milliseconds.

    .venv/bin/python bench/prior_gradient_speed.py

Writes bench/results/prior_gradient_speed.{json,md}.
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from bench_common import RESULTS, load_average, machine_record, markdown_header, write_results

from visnerf.config import FieldConfig, TrainConfig
from visnerf.representation.field import VisNerfField
from visnerf.runtime import keep_freed_blocks
from visnerf.training.regularizers import RegularizerWeights, backward_regularization, regularization


def nyx_sized_field(resolution: int) -> VisNerfField:
    cfg = FieldConfig(resolution=(resolution,) * 3, param_lengths=(3, 3, 5))
    return VisNerfField(cfg, torch.tensor([[-0.19] * 3, [0.19] * 3]))


def time_once(field: VisNerfField, weights: RegularizerWeights, way: str) -> float:
    field.zero_grad(set_to_none=True)
    t0 = time.perf_counter()
    if way == "autograd":
        sum(regularization(field, weights).values()).backward()
    else:
        backward_regularization(field, weights)
    return time.perf_counter() - t0


def write_markdown(path: Path, record: dict) -> None:
    r = record["results_ms"]
    lines = markdown_header("The priors' gradient on a Nyx-sized field", record) + [
        "",
        f"Field: {record['resolution']}^3, 16 density and 48 appearance components, parameter axes of 3, 3 and 5 "
        f"values; glibc keeping freed blocks as in training (`runtime.keep_freed_blocks`); weights of the trainer after its L1 switch: {record['weights']}. "
        f"{record['rounds']} rounds of {record['repeats']} calls each way, alternating; `.grad` set to None before each call.",
        "",
        "| way | median ms | min ms | max ms |",
        "| --- | --- | --- | --- |",
        *[f"| {way} | {v['median']:.2f} | {v['min']:.2f} | {v['max']:.2f} |" for way, v in r.items()],
        "",
        f"In place is {record['speedup']:.2f} times as fast (ratio of the medians).",
        "",
    ]
    path.write_text("\n".join(lines))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolution", type=int, default=170)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    keep_freed_blocks()  # as the trainer does on the CPU
    load_before = load_average()
    t = TrainConfig()
    weights = RegularizerWeights(t.l1_weight_rest, t.param_l1_weight, t.tv_weight_density,
                                 t.tv_weight_appearance, t.tv_weight_params)
    field = nyx_sized_field(args.resolution)
    for way in ("autograd", "in place"):  # warm-up: first-touch pages, kernels
        time_once(field, weights, way)
    times: dict[str, list[float]] = {"autograd": [], "in place": []}
    for _ in range(args.rounds):
        for way in times:
            times[way] += [1000 * time_once(field, weights, way) for _ in range(args.repeats)]
    results = {way: {"median": statistics.median(v), "min": min(v), "max": max(v)} for way, v in times.items()}
    record = {
        **machine_record(),
        "command": " ".join(["python bench/prior_gradient_speed.py", *sys.argv[1:]]),
        "load_average_1min": {"before": load_before, "after": load_average()},
        "resolution": args.resolution, "rounds": args.rounds, "repeats": args.repeats,
        "weights": {k: v for k, v in vars(weights).items() if v},
        "results_ms": results,
        "speedup": results["autograd"]["median"] / results["in place"]["median"],
    }
    write_results(Path(args.results), "prior_gradient_speed", record, write_markdown)
    print(f"autograd {results['autograd']['median']:.2f} ms, in place {results['in place']['median']:.2f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
