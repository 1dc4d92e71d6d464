"""Training steps of an opaque isosurface scene against a translucent volume, late in a run.

Each trained checkpoint is stepped as the end of its run does (its grid and occupancy, no
milestones left, the recipe it records: its step and its priors), the scenes in turn so that they
share the machine's noise: the isosurface with the samples behind opaque content dropped (the
product's step), the same without dropping them (``stop_eps`` 0, the step before), and the volume
with the product's step.
Reports the median milliseconds and the samples shaded and evaluated per step.

    .venv/bin/python bench/train_step_kinds.py --surface runs/eval/tangle_iso.safetensors \\
        --surface-data data/eval/tangle_iso_128 --volume runs/eval/vortex_tf1.safetensors \\
        --volume-data data/eval/vortex_tf1_128
"""

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import torch
from bench_common import RESULTS, alternate_steps, cpu_description, write_json

from visnerf.checkpoint import load_checkpoint
from visnerf.config import TrainConfig
from visnerf.data.datasets import load_dataset
from visnerf.training.trainer import Trainer


def late_trainer(ckpt: Path, data: Path, stop_eps: float | None, batch_rays: int) -> Trainer:
    """A trainer that steps the trained field of ``ckpt`` on ``data`` as the late phase of its run:
    the recipe the checkpoint records (its priors and step), with no milestones left. ``stop_eps``
    None keeps the recipe's."""
    field, meta = load_checkpoint(ckpt, torch.device("cpu"))
    res = max(field.resolution)
    recipe = dict(meta.provenance.get("recipe", {}))
    late = dict(iterations=10**9, resolution_init=res, resolution_final=res, upsample_at=(), occupancy_at=(),
                occupancy_refine_at=(), trim_every=10**9, batch_rays=batch_rays, l1_switch_iteration=0,
                weight_average_span=0.0)
    if stop_eps is not None:
        late["stop_eps"] = stop_eps
    cfg = TrainConfig.from_dict({**recipe, **late})
    render = dataclasses.replace(meta.render)
    return Trainer(load_dataset(data, "train"), None, cfg, torch.device("cpu"), render_cfg=render, init_field=field)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--surface", type=Path, required=True, help="checkpoint of an isosurface scene")
    ap.add_argument("--surface-data", type=Path, required=True)
    ap.add_argument("--volume", type=Path, required=True, help="checkpoint of a volume-rendered scene")
    ap.add_argument("--volume-data", type=Path, required=True)
    ap.add_argument("--batch-rays", type=int, default=TrainConfig.batch_rays)
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--steps", type=int, default=10, help="steps per scene and round")
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args()
    for path in (args.surface, args.surface_data, args.volume, args.volume_data):
        if not path.exists():
            ap.error(f"{path} does not exist")
    trainers = {
        "surface": late_trainer(args.surface, args.surface_data, None, args.batch_rays),
        "surface, every sample shaded": late_trainer(args.surface, args.surface_data, 0.0, args.batch_rays),
        "volume": late_trainer(args.volume, args.volume_data, None, args.batch_rays),
    }
    times, outputs = alternate_steps(trainers, args.rounds, args.steps, warm_up=True)
    rows = {k: {"ms_median": statistics.median(v), "samples_shaded": statistics.median(o["samples"] for o in outputs[k])}
            for k, v in times.items()}
    record = {
        "command": "python bench/train_step_kinds.py " + " ".join(sys.argv[1:]),
        "machine": f"{cpu_description()}, {torch.get_num_threads()} threads, torch {torch.__version__}",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "batch_rays": args.batch_rays, "rounds": args.rounds, "steps": args.steps, "scenes": rows,
        "surface_over_volume": rows["surface"]["ms_median"] / rows["volume"]["ms_median"],
        "surface_all_over_surface": rows["surface, every sample shaded"]["ms_median"] / rows["surface"]["ms_median"],
    }
    args.results.mkdir(parents=True, exist_ok=True)
    write_json(args.results / "train_step_kinds.json", record)
    lines = ["# A late training step: isosurface against volume", "",
             f"`{record['command']}`  ", f"{record['machine']}, {record['date']}; {args.batch_rays} rays a step, "
             f"{args.rounds} rounds of {args.steps} steps each, the scenes in turn.", "",
             "| step | ms (median) | samples shaded (median) |", "| --- | --- | --- |"]
    lines += [f"| {k} | {r['ms_median']:.1f} | {r['samples_shaded']:.0f} |" for k, r in rows.items()]
    lines += ["", f"Isosurface over volume: {record['surface_over_volume']:.2f}x; the isosurface shading every "
                  f"sample over dropping those behind opaque content: {record['surface_all_over_surface']:.2f}x.", ""]
    (args.results / "train_step_kinds.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
