"""Training speed: the plain training path against the accelerated one, same data, seed and budget.

- plain: ``TrainConfig(carve=False, mixed_precision=False)``: no space carving before the first
  iteration, decoder products in float32;
- accelerated: the ``TrainConfig`` defaults (space carving, bfloat16 decoder products where the
  device has native bfloat16; whether it did is recorded).

Both train on the same training frames with the same seed under the same budget of training seconds
(the trainer's clock: carving counts, validation does not), plain first, and validate every
``--validate-every`` training seconds on the same held-out frames (views 5, 17, 29 and 40 at every
setting, as bench/nyx_train.py holds out, plus its held-out settings on Nyx).
Records iterations, iterations per second, samples per iteration and validation PSNR against
training seconds, and compares the validation PSNR of the two at equal training time by linear
interpolation of the logged curves at the union of their validation times.

    .venv/bin/python bench/train_speed.py                                  # data/vortex_tf1, 5 min each
    .venv/bin/python bench/train_speed.py --data ../shared/data/nyx --minutes 10 --threads 1

Writes train_speed.json, train_speed.md and train_speed.png to --out-dir (bench/results).

With ``--ranks N``, training throughput (rays per second) on several processes instead
(``training.distributed``): one process on one thread, one process on N threads and N ranks of one
thread each under torchrun (gloo), side by side, ``--repeats`` rounds in turn, each run the product's
recipe (``recipe_trainer``) for ``--iterations`` steps of ``--batch-rays`` rays (the global batch: each
rank draws its share), no validation:

    .venv/bin/python bench/train_speed.py --ranks 2 --data data/eval/plume_static_128

Writes train_ranks.json and train_ranks.md to --out-dir.
"""

import visnerf  # noqa: F401  (before torch: it sets the OpenMP wait policy that torch reads once)

# isort: split
import argparse
import dataclasses
import gc
import json
import os
import socket
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from bench_common import (
    RESULTS,
    ROOT,
    fmt,
    holdout_for,
    load_average,
    machine_record,
    markdown_header,
    save_figure,
    write_json,
)
from matplotlib.figure import Figure

from visnerf.config import FieldConfig, HoldoutConfig, RenderConfig, TrainConfig
from visnerf.data.datasets import load_dataset
from visnerf.data.holdout import split_holdout
from visnerf.data.scene import SceneData
from visnerf.runtime import bf16_native, configure, release_free_memory
from visnerf.training.distributed import Launch, Ranks, leave_process_group
from visnerf.training.recipe import recipe_trainer
from visnerf.training.trainer import Trainer

TARGET_SPEEDUP = 3.0


@dataclass(frozen=True)
class Options:
    data: Path
    minutes: float
    """Training budget of each run (trainer clock: validation excluded)."""
    validate_every: float
    """Training seconds between validations."""
    val_images: int
    """Held-out frames rendered per validation."""
    seed: int
    threads: int | None
    resolution: int
    """Final voxels per axis."""
    batch_rays: int
    out_dir: Path
    ranks: int = 0
    """Ranks mode (``--ranks``): 0 for the plain-against-accelerated comparison."""
    iterations: int = 60
    """Steps of each run in ranks mode."""
    repeats: int = 2
    """Rounds of the ranks mode's runs, in turn."""
    rank_worker: Path | None = None
    """Where one internal run of the ranks mode writes its figures (``rank_worker``)."""


@dataclass(frozen=True)
class RunResult:
    name: str
    config: dict
    bf16_in_use: bool
    iterations: int
    train_seconds: float
    """Trainer clock at the end: training steps plus carving, no validation."""
    setup_seconds: float
    """Space carving before the first iteration (part of ``train_seconds``)."""
    wall_seconds: float
    """Construction and run in all, validation and grid updates included."""
    iterations_per_second: float
    samples_per_iteration: float | None
    """Valid ray samples evaluated per iteration (mean), as the trainer's step reports them."""
    curve: tuple[dict, ...]
    full_step_ratio: float | None = None
    """Full-quality spacing the run chose at its end (the last validation renders at it)."""
    """Logged rows: train_seconds, iteration, val_psnr, val_ssim, ..."""


class CountingTrainer(Trainer):
    """A Trainer that also sums the samples each step reports."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.samples_total = 0.0
        self.samples_reported = True

    def train_step(self) -> dict[str, float]:
        stats = super().train_step()
        if "samples" in stats:
            self.samples_total += float(stats["samples"])
        else:
            self.samples_reported = False
        return stats


def load_split(folder: Path) -> tuple[SceneData, SceneData, HoldoutConfig]:
    scene = load_dataset(folder, "train")
    holdout = holdout_for(scene)
    train, val = split_holdout(scene, holdout)
    if val is None:
        raise SystemExit(f"error: the hold-out {holdout} matches no frame of {folder}: nothing to validate on")
    return train, val, holdout


def variants(opts: Options) -> tuple[tuple[str, TrainConfig], ...]:
    base = TrainConfig(
        iterations=10**9, time_budget_s=opts.minutes * 60.0, batch_rays=opts.batch_rays,
        resolution_final=opts.resolution, validate_every_s=opts.validate_every,
        validate_max_images=opts.val_images, seed=opts.seed,
    )
    return ("plain", dataclasses.replace(base, carve=False, mixed_precision=False)), ("accelerated", base)


def train_once(
    name: str, cfg: TrainConfig, train: SceneData, val: SceneData, render_cfg: RenderConfig | None = None
) -> RunResult:
    device = torch.device("cpu")
    print(f"{name}: {cfg.time_budget_s:.0f} s budget, carve={cfg.carve}, mixed_precision={cfg.mixed_precision}",
          flush=True)
    t0 = time.perf_counter()
    trainer = CountingTrainer(train, val, cfg, device, render_cfg=render_cfg or RenderConfig())
    trainer.run(progress_bar=False, on_validate=lambda row: print(f"  {name}: {row}", flush=True))
    wall = time.perf_counter() - t0
    state = trainer.state
    samples = trainer.samples_total / state.iteration if trainer.samples_reported and state.iteration else None
    result = RunResult(
        name=name, config=cfg.to_dict(), bf16_in_use=cfg.mixed_precision and bf16_native(device),
        iterations=state.iteration, train_seconds=state.train_seconds, setup_seconds=trainer.setup_seconds,
        wall_seconds=wall, iterations_per_second=state.iteration / max(state.train_seconds, 1e-9),
        samples_per_iteration=samples, curve=tuple(dict(row) for row in state.log),
        full_step_ratio=trainer.render_cfg.full_step_ratio,
    )
    del trainer
    gc.collect()
    release_free_memory()
    return result


def curve_points(run: RunResult) -> tuple[np.ndarray, np.ndarray]:
    rows = [r for r in run.curve if r.get("val_psnr") is not None]
    return np.array([r["train_seconds"] for r in rows], float), np.array([r["val_psnr"] for r in rows], float)


def equal_time_rows(plain: RunResult, fast: RunResult) -> list[dict]:
    """Both curves interpolated linearly at every logged time where both have been validated."""
    tp, pp = curve_points(plain)
    ta, pa = curve_points(fast)
    if tp.size == 0 or ta.size == 0:
        return []
    lo, hi = max(tp[0], ta[0]), min(tp[-1], ta[-1])
    times = sorted({float(t) for t in np.concatenate([tp, ta]) if lo <= t <= hi})
    rows = []
    for t in times:
        a, b = float(np.interp(t, tp, pp)), float(np.interp(t, ta, pa))
        rows.append({"train_seconds": t, "plain_val_psnr": a, "accelerated_val_psnr": b, "difference": b - a})
    return rows


def write_markdown(path: Path, record: dict, runs: list[RunResult], rows: list[dict]) -> None:
    speedup = record["speedup_iterations_per_second"]
    lines = [
        *markdown_header("Training speed: plain against accelerated", record),
        "",
        f"Data: `{record['data']}`, {record['train_frames']} training frames, {record['val_frames']} held out "
        f"({record['holdout']}); up to {record['val_images']} of them rendered per validation, the same each time. Seed {record['seed']}, "
        f"budget {record['minutes']} min of training time each. Training time is the trainer's clock: training "
        "steps and space carving; validation, grid upsampling and occupancy updates run outside it (they are in "
        "the wall time).",
        "",
        "| run | carve | bf16 in use | iterations | training s | carving s | wall s | it/s | samples per iteration "
        "| final val PSNR dB |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in runs:
        final = r.curve[-1].get("val_psnr") if r.curve else None
        lines.append(
            f"| {r.name} | {r.config['carve']} | {r.bf16_in_use} | {r.iterations} | {fmt(r.train_seconds)} | "
            f"{fmt(r.setup_seconds)} | {fmt(r.wall_seconds)} | {fmt(r.iterations_per_second, 2)} | "
            f"{fmt(r.samples_per_iteration, 0)} | {fmt(final, 2)} |"
        )
    lines += [
        "",
        f"Iterations per second, accelerated / plain: **{fmt(speedup, 2)}x** (target at least {TARGET_SPEEDUP:.0f}x).",
        "",
        "Validation PSNR at equal training time (each curve interpolated linearly between its validations):",
        "",
        "| training s | plain dB | accelerated dB | accelerated minus plain dB |",
        "| --- | --- | --- | --- |",
    ]
    lines += [f"| {fmt(r['train_seconds'])} | {fmt(r['plain_val_psnr'], 2)} | {fmt(r['accelerated_val_psnr'], 2)} | "
              f"{fmt(r['difference'], 3)} |" for r in rows]
    if not rows:
        lines.append("| - | no common time: a run has no validation | | |")
    lines += ["", "![validation PSNR against training time](train_speed.png)", ""]
    path.write_text("\n".join(lines))


def plot(path: Path, runs: list[RunResult]) -> None:
    fig = Figure(figsize=(6.5, 4), layout="constrained")
    ax = fig.subplots()
    for run, style in zip(runs, ("s--", "o-"), strict=True):
        t, p = curve_points(run)
        ax.plot(t, p, style, label=f"{run.name} ({run.iterations_per_second:.2f} it/s)")
    ax.set_xlabel("training seconds (validation excluded)")
    ax.set_ylabel("validation PSNR (dB)")
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.grid(alpha=0.3)
    ax.legend()
    save_figure(fig, path)


RANK_VARIANTS = (("1 process, 1 thread", 1, 1), ("1 process, {n} threads", 1, None), ("{n} ranks, 1 thread each", None, 1))
"""(name, processes, threads per process) of the ranks mode; None stands for ``--ranks``."""


def timed(fn: Callable, spent: list[float]) -> Callable:
    """``fn``, appending the seconds of each call to ``spent``."""
    def call(*args, **kwargs):
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        spent.append(time.perf_counter() - t0)
        return out
    return call


def rank_worker(opts: Options, out: Path) -> int:
    """One run of the ranks mode (alone, or as one rank under torchrun): rank 0 writes its figures
    to ``out``. Threads come from VISNERF_THREADS."""
    ranks = Ranks.start(Launch.from_environment(), torch.device("cpu"))
    try:
        train = load_dataset(opts.data, "train")
        cfg = TrainConfig(iterations=opts.iterations, batch_rays=opts.batch_rays, seed=opts.seed)
        trainer = recipe_trainer(train, None, cfg, FieldConfig(), ranks.device, None,
                                 frozenset({"iterations", "batch_rays", "seed"}))
        trainer.distribute(ranks)
        steps: list[float] = []
        reduces: list[float] = []
        trainer.train_step = timed(trainer.train_step, steps)  # type: ignore[method-assign]
        ranks.average_gradients = timed(ranks.average_gradients, reduces)  # type: ignore[method-assign]
        t0, cpu0 = time.perf_counter(), time.process_time()
        trainer.run(progress_bar=False)
        loop = time.perf_counter() - t0
        cpu = torch.tensor([time.process_time() - cpu0], dtype=torch.float64)
        if ranks.world_size > 1:
            torch.distributed.all_reduce(cpu)  # CPU seconds of all ranks
    finally:
        leave_process_group()
    if ranks.is_main:
        late = steps[len(steps) // 2 :]  # at the final resolution (the schedule upsamples in its first quarter)
        write_json(out, {
            "processes": ranks.world_size, "threads": torch.get_num_threads(), "iterations": trainer.state.iteration,
            "batch_rays": opts.batch_rays, "resolution": list(trainer.field.resolution),
            "setup_seconds": trainer.setup_seconds, "loop_seconds": loop,
            "rays_per_second": trainer.state.iteration * opts.batch_rays / loop,
            "cpu_seconds": float(cpu), "rays_per_cpu_second": trainer.state.iteration * opts.batch_rays / float(cpu),
            "late_step_ms": 1000 * statistics.median(late),
            "late_rays_per_second": opts.batch_rays / statistics.median(late),
            "late_all_reduce_ms": 1000 * statistics.median(reduces[len(reduces) // 2 :]) if ranks.world_size > 1 else 0.0,
        })
    return 0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_ranks_variant(opts: Options, processes: int, threads: int, out: Path) -> dict:
    """One run of the ranks mode in a fresh process (or ``processes`` under torchrun)."""
    worker = [str(Path(__file__).resolve()), "--rank-worker", str(out), "--data", str(opts.data),
              "--iterations", str(opts.iterations), "--batch-rays", str(opts.batch_rays), "--seed", str(opts.seed)]
    launcher = [sys.executable] if processes == 1 else [
        sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", str(processes),
        "--master-addr", "127.0.0.1", "--master-port", str(free_port())]
    env = {**os.environ, "VISNERF_THREADS": str(threads), "OMP_NUM_THREADS": str(threads)}
    subprocess.run([*launcher, *worker], check=True, env=env)
    return json.loads(out.read_text())


def ranks_main(opts: Options) -> int:
    n = opts.ranks
    variants = [(name.format(n=n), p or n, t or n) for name, p, t in RANK_VARIANTS]
    record: dict = {"command": "python bench/train_speed.py " + " ".join(sys.argv[1:]), **machine_record(),
                    "data": str(opts.data), "iterations": opts.iterations, "batch_rays": opts.batch_rays,
                    "seed": opts.seed, "repeats": opts.repeats}
    loads = [load_average()]
    runs: dict[str, list[dict]] = {name: [] for name, _, _ in variants}
    opts.out_dir.mkdir(parents=True, exist_ok=True)
    for round_ in range(opts.repeats):
        for name, processes, threads in variants:
            print(f"round {round_ + 1}: {name}", flush=True)
            result = run_ranks_variant(opts, processes, threads, opts.out_dir / "train_ranks_run.json")
            runs[name].append({**result, "load_average_1min": load_average()})
            print(f"  {result['rays_per_second']:.0f} rays/s, {result['late_step_ms']:.0f} ms per late step", flush=True)
    (opts.out_dir / "train_ranks_run.json").unlink(missing_ok=True)
    loads.append(load_average())
    summary = []
    for name, processes, threads in variants:
        rs = runs[name]
        summary.append({"name": name, "processes": processes, "threads": threads,
                        **{key: statistics.median(r[key] for r in rs) for key in
                           ("rays_per_second", "rays_per_cpu_second", "late_rays_per_second", "late_step_ms",
                            "late_all_reduce_ms")}})
    base = summary[0]["rays_per_second"]
    for row in summary:
        row["speedup"] = row["rays_per_second"] / base
    record.update({"load_average_1min": {"before": loads[0], "after": loads[-1]}, "summary": summary, "runs": runs})
    write_json(opts.out_dir / "train_ranks.json", record)
    write_ranks_markdown(opts.out_dir / "train_ranks.md", record)
    print(f"wrote {opts.out_dir / 'train_ranks.json'} and .md")
    return 0


def write_ranks_markdown(path: Path, record: dict) -> None:
    first = next(iter(record["runs"].values()))[0]
    lines = [
        *markdown_header("Training throughput on several processes", record),
        "",
        f"Data: `{record['data']}` (the recipe's grid: {first['resolution']}), {record['iterations']} steps of "
        f"{record['batch_rays']} rays (the global batch) per run, seed {record['seed']}, no validation; "
        f"{record['repeats']} rounds of the three runs in turn, medians over the rounds. Rays per second: "
        "steps times the batch over the loop's wall time (upsampling and occupancy milestones included); "
        "late: the median step of the second half of the run, at the final resolution. All-reduce: the "
        "median time rank 0 spends in averaging gradients (waiting for the slower rank included). Rays per "
        "CPU second: the same rays over the CPU time of all the run's processes in the loop, a measure of the "
        "work each way costs that other jobs on the machine disturb less than wall time.",
        "",
        "| run | processes x threads | rays/s | rays per CPU s | late rays/s | late ms per step | of which all-reduce ms "
        "| rays/s against 1 x 1 |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in record["summary"]:
        lines.append(f"| {r['name']} | {r['processes']} x {r['threads']} | {fmt(r['rays_per_second'], 0)} | "
                     f"{fmt(r['rays_per_cpu_second'], 0)} | "
                     f"{fmt(r['late_rays_per_second'], 0)} | {fmt(r['late_step_ms'], 0)} | "
                     f"{fmt(r['late_all_reduce_ms'], 1)} | {fmt(r['speedup'], 2)}x |")
    lines += ["", "Each round's runs (rays/s, 1-min load average after the run):", ""]
    for name, rs in record["runs"].items():
        lines.append(f"- {name}: " + ", ".join(f"{r['rays_per_second']:.0f} (load {r['load_average_1min']})" for r in rs))
    path.write_text("\n".join(lines) + "\n")


def parse_args(argv: list[str] | None = None) -> Options:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT / "data" / "vortex_tf1"), help="dataset folder (default data/vortex_tf1)")
    ap.add_argument("--minutes", type=float, default=5.0, help="training minutes of each run (default 5)")
    ap.add_argument("--validate-every", type=float, default=30.0, help="training seconds between validations (default 30)")
    ap.add_argument("--val-images", type=int, default=TrainConfig.validate_max_images,
                    help=f"held-out frames per validation (default {TrainConfig.validate_max_images})")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: the usable cores)")
    ap.add_argument("--resolution", type=int, default=TrainConfig.resolution_final,
                    help=f"final voxels per axis (default {TrainConfig.resolution_final})")
    ap.add_argument("--batch-rays", type=int, default=TrainConfig.batch_rays,
                    help=f"rays per iteration (default {TrainConfig.batch_rays})")
    ap.add_argument("--out-dir", default=str(RESULTS), help="results folder (default bench/results)")
    ap.add_argument("--ranks", type=int, default=0, metavar="N",
                    help="ranks mode: 1 process x 1 thread, 1 x N threads and N ranks x 1 thread (torchrun)")
    ap.add_argument("--iterations", type=int, default=60, help="steps of each run in ranks mode (default 60)")
    ap.add_argument("--repeats", type=int, default=2, help="rounds of the ranks mode's runs (default 2)")
    ap.add_argument("--rank-worker", default=None, metavar="OUT.json", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.minutes <= 0 or a.validate_every <= 0 or a.val_images < 1:
        ap.error("--minutes and --validate-every must be positive, --val-images at least 1")
    if a.ranks < 0 or a.ranks == 1 or a.iterations < 1 or a.repeats < 1:
        ap.error("--ranks must be 2 or more, --iterations and --repeats at least 1")
    return Options(Path(a.data), a.minutes, a.validate_every, a.val_images, a.seed, a.threads, a.resolution,
                   a.batch_rays, Path(a.out_dir), a.ranks, a.iterations, a.repeats,
                   None if a.rank_worker is None else Path(a.rank_worker))


def main(argv: list[str] | None = None) -> int:
    opts = parse_args(argv)
    if opts.rank_worker is not None:
        return rank_worker(opts, opts.rank_worker)
    if opts.ranks:
        return ranks_main(opts)
    configure(opts.threads)
    train, val, holdout = load_split(opts.data)
    record: dict = {"command": "python bench/train_speed.py " + " ".join(sys.argv[1:]), **machine_record(),
                    "data": str(opts.data), "train_frames": train.n_frames, "val_frames": val.n_frames,
                    "holdout": f"views {list(holdout.views)}, settings {[list(x) for x in holdout.settings]}", "val_images": opts.val_images, "seed": opts.seed,
                    "minutes": opts.minutes}
    loads = [load_average()]
    runs = []
    for name, cfg in variants(opts):
        runs.append(train_once(name, cfg, train, val))
        loads.append(load_average())
    plain, fast = runs
    rows = equal_time_rows(plain, fast)
    record.update({
        "load_average_1min": {"before": loads[0], "between": loads[1], "after": loads[2]},
        "speedup_iterations_per_second": fast.iterations_per_second / max(plain.iterations_per_second, 1e-12),
        "equal_time": rows,
        "runs": [dataclasses.asdict(r) for r in runs],
    })
    opts.out_dir.mkdir(parents=True, exist_ok=True)
    write_json(opts.out_dir / "train_speed.json", record)
    write_markdown(opts.out_dir / "train_speed.md", record, runs, rows)
    plot(opts.out_dir / "train_speed.png", runs)
    print(f"it/s plain {plain.iterations_per_second:.2f}, accelerated {fast.iterations_per_second:.2f} "
          f"({record['speedup_iterations_per_second']:.2f}x)")
    print(f"wrote {opts.out_dir / 'train_speed.json'}, .md and .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
