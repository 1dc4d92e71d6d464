"""A late training step: the fused CPU step against the torch path, side by side, on trained models.

Each ``--scene CHECKPOINT DATA`` is stepped as the end of its run does (its grid and occupancy, the
recipe it records, no milestones left), by two trainers on two copies of its field: the fused step
(``training.fused_step``, the product on the CPU) and the torch path (the step before it, which
every device keeps). Both draw the same rays from the same seed. Timing alternates between them,
``--rounds`` rounds of ``--steps`` steps each, after one untimed step each. Reports the median
milliseconds of a step, rays and samples a second, and the ratio.

With ``--loss-steps N`` the two trainers then train ``N`` further steps each from the same field
and seed (one after the other), and the report compares their photometric loss in windows of
``--window`` steps: the fused step's lazy optimizer and priors against the torch path's dense ones.

    .venv/bin/python bench/train_step.py --scene runs/nyx.safetensors ../shared/data/nyx \\
        --scene runs/lit512.safetensors data/lit_series_512 --loss-steps 2000

Writes train_step.json and train_step.md to --results (bench/results).

On a GPU (the project never needs one), ``--device cuda`` steps the first scene's torch path (the
one every device has) at each ``--batches`` size, ``--steps`` steps after ``--warm-up`` untimed
ones, then times full-quality frames at each ``--frame-sizes``, and writes cuda_check.json and
cuda_check.md with the GPU named:

    python bench/train_step.py --device cuda --scene runs/nyx.safetensors ../shared/data/nyx \\
        --steps 20 --results bench/results/cuda_check
"""

import visnerf  # noqa: F401  (before torch: it sets the OpenMP wait policy that torch reads once)

# isort: split
import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from bench_common import (
    RESULTS,
    alternate_steps,
    late_trainer,
    load_average,
    machine_record,
    markdown_header,
    write_json,
    write_results,
)

from visnerf.config import TrainConfig
from visnerf.data.cameras import orbit_c2w
from visnerf.data.datasets import load_dataset
from visnerf.inference import load_scene
from visnerf.runtime import configure
from visnerf.training.trainer import Trainer

PATHS = ("fused", "torch")


def loss_windows(trainer: Trainer, steps: int, window: int) -> tuple[list[float], float]:
    """Mean photometric loss of each ``window`` steps of ``steps``, and the seconds they took."""
    losses, t0 = [], time.perf_counter()
    for _ in range(steps):
        losses.append(trainer.train_step()["mse"])
        trainer.state.iteration += 1
    seconds = time.perf_counter() - t0
    return [float(np.mean(losses[i:i + window])) for i in range(0, steps, window)], seconds


def measure_scene(ckpt: Path, data: Path, args: argparse.Namespace) -> dict:
    scene = load_dataset(data, "train")
    trainers = {path: late_trainer(ckpt, scene, args.batch_rays, path == "fused") for path in PATHS}
    times, outputs = alternate_steps(trainers, args.rounds, args.steps, warm_up=True)
    row: dict = {"checkpoint": str(ckpt), "data": str(data), "image": f"{scene.intrinsics.width}x{scene.intrinsics.height}",
                 "frames": scene.n_frames, "resolution": list(trainers["fused"].field.resolution)}
    for path in PATHS:
        ms = statistics.median(times[path])
        samples = statistics.median(o["samples"] for o in outputs[path])
        row[path] = {"ms_median": ms, "ms_min": min(times[path]), "ms_max": max(times[path]),
                     "samples_median": samples, "rays_per_s": args.batch_rays / ms * 1000.0,
                     "samples_per_s": samples / ms * 1000.0}
    row["speedup"] = row["torch"]["ms_median"] / row["fused"]["ms_median"]
    if args.loss_steps > 0:
        fresh = {path: late_trainer(ckpt, scene, args.batch_rays, path == "fused") for path in PATHS}
        row["loss"] = {}
        for path, trainer in fresh.items():
            windows, seconds = loss_windows(trainer, args.loss_steps, args.window)
            row["loss"][path] = {"windows": windows, "seconds": seconds}
        fused, plain = (np.array(row["loss"][p]["windows"]) for p in PATHS)
        row["loss"]["fused_over_torch"] = (fused / plain).tolist()
    return row


def write_markdown(path: Path, record: dict) -> None:
    lines = markdown_header("A late training step: fused against the torch path", record)
    lines += ["", f"{record['batch_rays']} rays a step, {record['rounds']} rounds of {record['steps']} steps each "
                  "path, in turn, after one untimed step each; each path on its own copy of the field.", "",
              "| scene | image | grid | path | ms a step (median) | rays / s | samples a step | samples / s | speedup |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for row in record["scenes"]:
        name = Path(row["checkpoint"]).stem
        grid = "x".join(str(r) for r in row["resolution"])
        for kind in PATHS:
            r = row[kind]
            speed = f"{row['speedup']:.2f}x" if kind == "fused" else ""
            lines.append(f"| {name} | {row['image']} | {grid} | {kind} | {r['ms_median']:.1f} | {r['rays_per_s']:,.0f} | "
                         f"{r['samples_median']:,.0f} | {r['samples_per_s']:,.0f} | {speed} |")
    for row in record["scenes"]:
        if "loss" not in row:
            continue
        name = Path(row["checkpoint"]).stem
        loss = row["loss"]
        lines += ["", f"**{name}: photometric loss over {record['loss_steps']} further steps** (mean of each "
                      f"{record['window']} steps; fused {loss['fused']['seconds']:.0f} s, torch "
                      f"{loss['torch']['seconds']:.0f} s in all)", "",
                  "| steps | fused | torch | fused / torch |", "| --- | --- | --- | --- |"]
        for i, (a, b, q) in enumerate(zip(loss["fused"]["windows"], loss["torch"]["windows"], loss["fused_over_torch"],
                                          strict=True)):
            lines.append(f"| {i * record['window']}-{(i + 1) * record['window'] - 1} | {a:.6f} | {b:.6f} | {q:.3f} |")
    path.write_text("\n".join(lines) + "\n")


def synchronise(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def step_rates(args: argparse.Namespace, device: torch.device) -> list[dict]:
    """The torch path's step at each ``--batches`` size on ``device``, synchronised around each step."""
    ckpt, data = (Path(p) for p in args.scene[0])
    scene = load_dataset(data, "train")
    rows = []
    for batch in args.batches:
        trainer = late_trainer(ckpt, scene, batch, device=device)
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
    """Full-quality frames of the first checkpoint at each ``--frame-sizes`` (random views and values)."""
    scene = load_scene(args.scene[0][0], device)
    g = np.random.default_rng(0)
    distance = scene.info.camera.get("distance", 2.0)
    rows = []
    for size in args.frame_sizes:
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


def device_check(args: argparse.Namespace) -> int:
    """On a GPU (``--device cuda``): rays a second against rays a step, and frame times."""
    device = torch.device(args.device)
    gpu = torch.cuda.get_device_name(device) if device.type == "cuda" else args.device
    record = {**machine_record(), "gpu": gpu, "command": "python bench/train_step.py " + " ".join(sys.argv[1:]),
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", nargs=2, action="append", metavar=("CHECKPOINT", "DATA"), required=True)
    ap.add_argument("--batch-rays", type=int, default=TrainConfig.batch_rays)
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--steps", type=int, default=10, help="steps per path and round")
    ap.add_argument("--loss-steps", type=int, default=0, help="further steps of each path compared by loss")
    ap.add_argument("--window", type=int, default=200)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--device", default="cpu", help="another device (cuda): the torch path at each --batches, "
                                                    "frames at each --frame-sizes, into cuda_check.md")
    ap.add_argument("--batches", type=int, nargs="+", default=[2048, 8192, 32768, 131072])
    ap.add_argument("--warm-up", type=int, default=3, help="untimed steps before each batch size (--device)")
    ap.add_argument("--frame-sizes", type=int, nargs="+", default=[256, 800])
    ap.add_argument("--frames", type=int, default=10, help="frames timed at each size (--device)")
    args = ap.parse_args()
    for ckpt, data in args.scene:
        for p in (ckpt, data):
            if not Path(p).exists():
                ap.error(f"{p} does not exist")
    if args.device != "cpu":
        args.results.mkdir(parents=True, exist_ok=True)
        return device_check(args)
    configure(args.threads)
    record = {**machine_record(), "command": "python bench/train_step.py " + " ".join(sys.argv[1:]),
              "batch_rays": args.batch_rays, "rounds": args.rounds, "steps": args.steps,
              "loss_steps": args.loss_steps, "window": args.window, "load_average_1min": {"before": load_average()}}
    record["scenes"] = [measure_scene(Path(c), Path(d), args) for c, d in args.scene]
    record["load_average_1min"]["after"] = load_average()
    write_results(args.results, "train_step", record, write_markdown)
    print(Path(args.results / "train_step.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
