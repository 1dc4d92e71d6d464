"""Training steps with the decoders compiled by torch.compile (Inductor, CPU) against the product's.

A trained checkpoint is stepped as the end of its run does (``train_step_kinds.late_trainer``), two
trainers on two copies of the field, in turn: the product's step, and the same step with
``density_from_features`` and ``color_from_features`` (encodings, the two decoders, softplus and
sigmoid: everything between the VM lookups and the compositing) compiled with dynamic shapes (the
samples per step vary). The compiled trainer first takes ``--warm-up`` untimed steps (compiling
happens there; its seconds are reported). Reports the median milliseconds of a step, the ratio, and
the largest difference of the two trainers' losses on the first step, taken from the same field and
the same rays.

    .venv/bin/python bench/train_compile.py --checkpoint runs/nyx_hour_1t.safetensors --data ../shared/data/nyx
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from bench_common import RESULTS, alternate_steps, cpu_description, write_json
from train_step_kinds import late_trainer

from visnerf.config import TrainConfig


def compile_decoders(trainer) -> None:  # noqa: ANN001 - a Trainer
    field = trainer.field
    field.density_from_features = torch.compile(field.density_from_features, dynamic=True)
    field.color_from_features = torch.compile(field.color_from_features, dynamic=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--batch-rays", type=int, default=TrainConfig.batch_rays)
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--steps", type=int, default=10, help="steps per trainer and round")
    ap.add_argument("--warm-up", type=int, default=8, help="untimed steps of each trainer first")
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args()
    for path in (args.checkpoint, args.data):
        if not path.exists():
            ap.error(f"{path} does not exist")
    plain = late_trainer(args.checkpoint, args.data, TrainConfig.stop_eps, args.batch_rays)
    compiled = late_trainer(args.checkpoint, args.data, TrainConfig.stop_eps, args.batch_rays)
    compile_decoders(compiled)
    # Both trainers seed their ray generator alike: the first steps draw the same rays from the same
    # field, so their losses agree as far as the compiled decoders do.
    first = {"product": plain.train_step()}
    t0 = time.perf_counter()
    first["compiled decoders"] = compiled.train_step()
    compile_s = time.perf_counter() - t0
    for _ in range(args.warm_up):
        plain.train_step()
        t0 = time.perf_counter()
        compiled.train_step()
        compile_s += time.perf_counter() - t0
    times, _ = alternate_steps({"product": plain, "compiled decoders": compiled}, args.rounds, args.steps)
    rows = {k: statistics.median(v) for k, v in times.items()}
    record = {
        "command": "python bench/train_compile.py " + " ".join(sys.argv[1:]),
        "machine": f"{cpu_description()}, {torch.get_num_threads()} threads, torch {torch.__version__}",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "batch_rays": args.batch_rays, "rounds": args.rounds, "steps": args.steps, "warm_up": args.warm_up,
        "ms_median": rows, "compiled_over_product": rows["compiled decoders"] / rows["product"],
        "warm_up_seconds_compiled": compile_s, "first_step": first,
    }
    args.results.mkdir(parents=True, exist_ok=True)
    write_json(args.results / "train_compile.json", record)
    lines = ["# Training steps with compiled decoders", "", f"`{record['command']}`  ",
             f"{record['machine']}, {record['date']}; {args.batch_rays} rays a step, {args.rounds} rounds of "
             f"{args.steps} steps each, in turn, after {args.warm_up} untimed steps each.", "",
             "| step | ms (median) |", "| --- | --- |"]
    lines += [f"| {k} | {v:.1f} |" for k, v in rows.items()]
    lines += ["", f"Compiled over the product: {record['compiled_over_product']:.3f}x; the compiled trainer's first "
                  f"{args.warm_up + 1} steps took {compile_s:.1f} s. First step: {first}.", ""]
    (args.results / "train_compile.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
