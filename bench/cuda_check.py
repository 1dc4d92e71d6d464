"""What a GPU does with the product: training rays per second against the rays a step, and frame times.

On a lent GPU (the project never needs one): a trained checkpoint is stepped as the end of its
run does (``bench_common.late_trainer``, the torch path every device has) at each ``--batches``
size in turn, ``--steps`` steps each after ``--warm-up`` untimed ones, synchronised around each
step; then full-quality frames of the same checkpoint at each ``--sizes`` (random views and
parameter values, the first untimed). Reports the median step time, rays and samples a second,
and the median frame time, with the GPU named.

    python bench/cuda_check.py --checkpoint runs/nyx.safetensors --data ../shared/data/nyx --results bench/results/cuda_check

Writes cuda_check.json and cuda_check.md to --results.
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from bench_common import late_trainer, machine_record, write_json

from visnerf.data.cameras import orbit_c2w
from visnerf.data.datasets import load_dataset
from visnerf.inference import load_scene


def synchronise(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def step_rates(args: argparse.Namespace, device: torch.device) -> list[dict]:
    scene = load_dataset(args.data, "train")
    rows = []
    for batch in args.batches:
        trainer = late_trainer(args.checkpoint, scene, batch, device=device)
        for _ in range(args.warm_up):
            trainer.train_step()
        times, samples = [], []
        for _ in range(args.steps):
            synchronise(device)
            t0 = time.perf_counter()
            stats = trainer.train_step()
            synchronise(device)
            times.append(time.perf_counter() - t0)
            samples.append(stats["samples"])
        ms = 1000 * statistics.median(times)
        rows.append({"batch_rays": batch, "ms_median": ms, "rays_per_s": batch / ms * 1000,
                     "samples_per_s": statistics.median(samples) / ms * 1000, "samples_median": statistics.median(samples)})
        print(rows[-1], flush=True)
        del trainer
        if device.type == "cuda":
            torch.cuda.empty_cache()
    return rows


def frame_times(args: argparse.Namespace, device: torch.device) -> list[dict]:
    scene = load_scene(args.checkpoint, device)
    g = np.random.default_rng(0)
    distance = scene.info.camera.get("distance", 2.0)
    rows = []
    for size in args.sizes:
        times = []
        for i in range(args.frames + 1):
            c2w = orbit_c2w(float(g.uniform(-180, 180)), float(g.uniform(-60, 60)), distance)
            params = {a.name: float(g.uniform(a.min, a.max)) for a in scene.info.params}
            synchronise(device)
            t0 = time.perf_counter()
            scene.render(c2w, 30.0, size, size, params)
            synchronise(device)
            if i > 0:  # the first builds the occupancy and the kernels
                times.append(time.perf_counter() - t0)
        rows.append({"size": size, "ms_median": 1000 * statistics.median(times), "frames": args.frames})
        print(rows[-1], flush=True)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--batches", type=int, nargs="+", default=[2048, 8192, 32768, 131072])
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--warm-up", type=int, default=3)
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 800])
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--results", type=Path, required=True)
    args = ap.parse_args()
    device = torch.device(args.device)
    gpu = torch.cuda.get_device_name(device) if device.type == "cuda" else "none"
    record = {**machine_record(), "gpu": gpu, "command": "python bench/cuda_check.py " + " ".join(sys.argv[1:]),
              "steps": step_rates(args, device), "frames": frame_times(args, device)}
    write_json(args.results / "cuda_check.json", record)
    lines = ["# Training and frames on a GPU", "", f"`{record['command']}`  ",
             f"{gpu}; {record['machine']}, torch {record['torch']}, {record['date']}.", "",
             "| rays a step | ms a step (median) | rays / s | samples / s |", "| --- | --- | --- | --- |"]
    lines += [f"| {r['batch_rays']} | {r['ms_median']:.1f} | {r['rays_per_s']:,.0f} | {r['samples_per_s']:,.0f} |"
              for r in record["steps"]]
    lines += ["", "| frame | ms (median) |", "| --- | --- |"]
    lines += [f"| {r['size']}x{r['size']} full quality | {r['ms_median']:.1f} |" for r in record["frames"]]
    (args.results / "cuda_check.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
