"""Does a depth term on the rays that hit content shorten training of an opaque scene? The same
pycinema database (depth in every ``.h5`` image) trained side by side, with and without it.

    python bench/depth_term.py --scene tangle_static --res 100 --views 90 --minutes 3 --weights 0,0.3,3

The term: for up to ``--depth-rays`` rays of each batch whose pixel records a depth d, the
compositing weights' spread about it, ``sum_i w_i (t_i - d)^2 / D^2`` (``D`` the box diagonal),
mean over those rays, times the weight; it only draws a ray's weight towards its recorded
surface. Its extra forward and backward pass is training time. Each arm trains for the same wall
time with the product's recipe otherwise; every ninth view is held out. Writes
``depth_term.json`` and ``.md``.
"""

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from bench_common import load_average, machine_record, markdown_header, render_frame, write_results

from visnerf.config import FieldConfig, HoldoutConfig, TrainConfig
from visnerf.data.datasets import load_dataset
from visnerf.data.holdout import split_holdout
from visnerf.evaluation.metrics import psnr
from visnerf.inference import load_scene
from visnerf.rendering.renderer import _shade_samples, place_samples
from visnerf.training.recipe import recipe_trainer


def add_depth_term(trainer, weight: float, max_rays: int) -> None:  # noqa: ANN001
    """Before each optimizer step, back-propagate the depth term of the batch just drawn."""
    scene = trainer.scene
    assert scene.depths is not None, "the database holds no depth"
    diagonal = float((scene.bbox[1] - scene.bbox[0]).norm())
    draw = trainer.sampler.sample
    drawn = {}

    def sample(n: int, *args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        drawn["batch"] = draw(n, *args, **kwargs)
        return drawn["batch"]

    def depth_backward() -> None:
        batch = drawn["batch"]
        depth = scene.depths[batch.frame, batch.py, batch.px]  # [n]
        rows = torch.isfinite(depth).nonzero()[:, 0][:max_rays]
        if rows.numel() == 0:
            return
        rays_o, rays_d = batch.rays_o[rows], batch.rays_d[rows]
        field = trainer.field
        samples = place_samples(field, rays_o, rays_d, trainer.step_size(), trainer.render_cfg.max_samples,
                                field.occupancy, trainer.generator, None)
        q_d, q_a = field.param_features(batch.params[rows])
        tau0 = torch.zeros(rows.numel(), dtype=rays_d.dtype)
        _, _, w = _shade_samples(field, rays_d, samples.points, samples.deltas, samples.valid, q_d, q_a, tau0,
                                 trainer.render_cfg.weight_threshold, None, samples.sigma, None)  # w: [m, s]
        t = ((samples.points - rays_o[:, None]) * rays_d[:, None]).sum(-1) / (rays_d * rays_d).sum(-1, keepdim=True)
        spread = (w * samples.valid * (t - depth[rows].to(t)[:, None]) ** 2).sum(-1) / diagonal**2  # [m]
        (weight * spread.mean()).backward()

    def wrap_step() -> None:
        step = trainer.optimizer.step

        def step_with_depth(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            depth_backward()
            return step(*args, **kwargs)

        trainer.optimizer.step = step_with_depth

    rebuild = trainer._rebuild_optimizer

    def rebuild_and_wrap() -> None:
        rebuild()
        wrap_step()

    trainer.sampler.sample = sample
    trainer._rebuild_optimizer = rebuild_and_wrap
    wrap_step()


def measure(weight: float, opts: argparse.Namespace, data: Path, work: Path) -> dict:
    held = tuple(range(0, opts.views, 9))
    train, val = split_holdout(load_dataset(data), HoldoutConfig(views=held))
    assert val is not None
    torch.set_num_threads(opts.threads)
    cfg = TrainConfig(time_budget_s=60.0 * opts.minutes)
    trainer = recipe_trainer(train, None, cfg, FieldConfig(), torch.device("cpu"))
    if weight > 0:
        add_depth_term(trainer, weight, opts.depth_rays)
    started = time.perf_counter()
    trainer.run(progress_bar=False)
    seconds = time.perf_counter() - started
    ckpt = trainer.save(work / f"depth_{weight:g}.safetensors")
    scene = load_scene(ckpt)
    scores = [psnr(*render_frame(scene, val, i, opts.res, opts.res)) for i in range(val.n_frames)]
    return {"depth_weight": weight, "held_out_frames": val.n_frames, "held_out_psnr": float(np.mean(scores)),
            "iterations": trainer.state.iteration, "wall_seconds": round(seconds, 1)}


def write_markdown(path: Path, record: dict) -> None:
    lines = markdown_header("A depth term on the rays that hit content", record)
    lines += ["", "| depth weight | held-out PSNR (dB) | steps | wall (s) |", "| --- | --- | --- | --- |"]
    for row in record["rows"]:
        lines.append(f"| {row['depth_weight']:g} | {row['held_out_psnr']:.2f} | {row['iterations']} | "
                     f"{row['wall_seconds']} |")
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="tangle_static")
    ap.add_argument("--res", type=int, default=100)
    ap.add_argument("--views", type=int, default=90)
    ap.add_argument("--minutes", type=float, default=3.0)
    ap.add_argument("--weights", default="0,0.3,3")
    ap.add_argument("--depth-rays", type=int, default=1024)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("bench/results/depth_term"))
    opts = ap.parse_args()
    record = {**machine_record(), "command": "python " + " ".join(sys.argv), "rows": []}
    load = {"before": load_average()}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        subprocess.run([sys.executable, "-m", "visnerf.cli", "make-scene", opts.scene, "--out", str(work / "db"),
                        "--res", str(opts.res), "--views", str(opts.views), "--test-views", "2", "--quiet",
                        "--format", "cinema", "--convention", "pycinema"], check=True)
        for weight in (float(w) for w in opts.weights.split(",")):
            record["rows"].append(measure(weight, opts, work / "db" / "train.cdb", work))
            print(record["rows"][-1], file=sys.stderr)
    load["after"] = load_average()
    record["load_average_1min"] = load
    write_results(opts.out, "depth_term", record, write_markdown)


if __name__ == "__main__":
    main()
