"""The empty-space walk with both ends of every ray in one loop, against one loop per end.

``EmptySpace.sample_window`` finds each ray's first and last lattice sample near content by
jumping over empty blocks (``EmptySpace.walk``, up to 24 jumps). Each jump is a dozen small tensor
operations over the rays still walking, so the walk costs about a fixed time per jump and
operation rather than per ray. Walking the forward and the backward end of every ray in one batch
halves the number of loop passes; walking them one after the other (the backward walk bounded by
the forward result) is what the walk did before. From a trained Nyx checkpoint this times both on
the same rays, alternating over ``--rounds``: training batches (``trainer.occupied_windows``,
``near = 1``, the recipe's 2048 rays) and the rays of held-out frames at their size (``near = 0``, as a
frame is rendered). For scale it also times the late-phase training step (``nyx_train.late_phase_trainer``).

    python bench/empty_space_walk.py --checkpoint runs/nyx_hour_onechunk.safetensors

Writes bench/results/empty_space_walk.{json,md}.
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from bench_common import (
    add_trained_model_args,
    alternate_steps,
    evenly_spaced,
    load_average,
    machine_record,
    markdown_header,
    nyx_split,
    require_checkpoint,
    step_time_summary,
    write_results,
)
from nyx_train import NYX_LATE_PHASE_STEP, NYX_MICRO_BATCH_SAMPLES, late_phase_trainer

from visnerf.data.cameras import image_rays
from visnerf.inference import load_scene
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.renderer import empty_space_of, ray_windows

Window = tuple[torch.Tensor, torch.Tensor]


def walk_each_end(space: EmptySpace, rays: dict, near: int) -> Window:
    """The walk one end after the other: forward from the box entry, then backward from the box
    exit down to the forward result."""
    up = torch.ones_like(rays["first"])
    first = space.walk(rays["o"], rays["d"], rays["t_near"], rays["step"], rays["first"], rays["last"], up, near)
    last = space.walk(rays["o"], rays["d"], rays["t_near"], rays["step"], rays["last"], first, -up, near)
    return first, last


def walk_both_ends(space: EmptySpace, rays: dict, near: int) -> Window:
    return space.sample_window(rays["o"], rays["d"], rays["t_near"], rays["step"], rays["first"], rays["last"], near)


WALKS = {"one loop per end": walk_each_end, "both ends in one loop": walk_both_ends}


def ray_set(field, rays_o: torch.Tensor, rays_d: torch.Tensor, step: float) -> dict:  # noqa: ANN001
    """Rays with their whole lattice window through the box, where ``occupied_windows`` and
    ``ray_windows`` start their walks."""
    box = ray_windows(field, rays_o, rays_d, step, None, None)
    return {"o": rays_o, "d": rays_d, "t_near": box.t_near, "step": step, "first": box.first, "last": box.last}


def frame_rays(field, frames, i: int, step: float) -> dict:  # noqa: ANN001
    """The rays of held-out frame ``i`` at its camera and native size."""
    o, d = (r.reshape(-1, 3) for r in image_rays(frames.c2w[i].float(), frames.intrinsics))
    return ray_set(field, o, d, step)


def time_walks(space: EmptySpace, ray_sets: list[dict], near: int, rounds: int) -> dict[str, dict]:
    """Per walk: the median milliseconds per ray set over ``rounds`` alternating rounds, the
    window samples it leaves, and how many rays get the window of the first walk."""
    ms: dict[str, list[float]] = {name: [] for name in WALKS}
    windows: dict[str, list[Window]] = {name: [] for name in WALKS}
    for rays in ray_sets[:1]:
        for walk in WALKS.values():
            walk(space, rays, near)  # warm-up
    for r in range(rounds):
        for name, walk in WALKS.items():
            for rays in ray_sets:
                t0 = time.perf_counter()
                window = walk(space, rays, near)
                ms[name].append(1000 * (time.perf_counter() - t0))
                if r == 0:
                    windows[name].append(window)
    reference = windows[next(iter(WALKS))]
    out = {}
    for name in WALKS:
        samples = sum(int((w[1] - w[0] + 1).clamp_min(0).sum()) for w in windows[name])
        same = sum(int(((w[0] == v[0]) & (w[1] == v[1]) | (w[0] > w[1]) & (v[0] > v[1])).sum())
                   for w, v in zip(windows[name], reference, strict=True))
        rays = sum(int(w[0].numel()) for w in windows[name])
        out[name] = {**step_time_summary(ms[name]), "window_samples_per_set": samples / len(ray_sets),
                     "rays_per_set": rays / len(ray_sets), "same_window_fraction": same / rays}
    return out


def write_markdown(path: Path, record: dict) -> None:
    lines = markdown_header("The empty-space walk: both ends in one loop against one loop per end", record) + [
        "",
        f"Checkpoint: `{record['checkpoint']}` (grid {record['resolution']}, occupancy grid {record['occupancy_shape']}); "
        f"{record['rounds']} alternating rounds. A late-phase training step ({record['step']['batch_rays']} rays, one "
        f"micro-batch) took {record['step']['median_ms']:.1f} ms (median of {record['step']['steps']}).",
        "",
        "| rays | walk | rays per set | ms per set (median) | fastest | against one loop per end | window samples per set | same window as one loop per end |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for kind, walks in record["walks"].items():
        base = walks["one loop per end"]["median_ms"]
        for name, w in walks.items():
            lines.append(f"| {kind} | {name} | {w['rays_per_set']:.0f} | {w['median_ms']:.2f} | {w['min_ms']:.2f} | "
                         f"{base / w['median_ms']:.2f}x | {w['window_samples_per_set']:.0f} | "
                         f"{100 * w['same_window_fraction']:.2f} % |")
    lines += ["", "Both walks leave the same windows on rays with content; they may differ only on a ray "
              "whose forward walk ran out of jumps, where the backward walk is no longer bounded by it.", ""]
    path.write_text("\n".join(lines))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_trained_model_args(ap, "nyx_hour_onechunk.safetensors")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--batches", type=int, default=20, help="training batches per round")
    ap.add_argument("--frames", type=int, default=4, help="held-out frames per round")
    ap.add_argument("--steps", type=int, default=30, help="late-phase training steps timed for scale")
    args = ap.parse_args()
    require_checkpoint(ap, args.checkpoint)
    load_before = load_average()
    train, val = nyx_split(args.data)
    field = load_scene(Path(args.checkpoint), torch.device("cpu")).field
    trainer = late_phase_trainer(train, field, NYX_MICRO_BATCH_SAMPLES, lr_factors=0.0, lr_networks=0.0,
                                 **NYX_LATE_PHASE_STEP)
    space = empty_space_of(field)
    if space is None:
        ap.error(f"{args.checkpoint} has no occupancy grid to walk")
    step = trainer.step_size()
    batches = []
    for _ in range(args.batches):
        b = trainer.sampler.sample(trainer.cfg.batch_rays)
        batches.append(ray_set(field, b.rays_o, b.rays_d, step))
    frames = [frame_rays(field, val, i, step) for i in evenly_spaced(val.n_frames, args.frames)]
    walks = {"training batch (near = 1)": time_walks(space, batches, 1, args.rounds),
             "held-out frame (near = 0)": time_walks(space, frames, 0, args.rounds)}
    for _ in range(5):  # untimed: oneDNN's kernels and the allocator's blocks
        trainer.train_step()
    times, _ = alternate_steps({"step": trainer}, 1, args.steps)
    record = {
        **machine_record(),
        "command": "python bench/empty_space_walk.py " + " ".join(sys.argv[1:]),
        "load_average_1min": {"before": load_before, "after": load_average()},
        "checkpoint": args.checkpoint, "resolution": list(field.resolution),
        "occupancy_shape": list(space.shape), "rounds": args.rounds, "walks": walks,
        "step": {"batch_rays": trainer.cfg.batch_rays, "steps": args.steps,
                 "median_ms": statistics.median(times["step"])},
    }
    write_results(Path(args.results), "empty_space_walk", record, write_markdown)
    for kind, by_walk in walks.items():
        for name, w in by_walk.items():
            print(f"{kind}, {name}: {w['median_ms']:.2f} ms, same window {100 * w['same_window_fraction']:.2f} %")
    print(f"late-phase step: {record['step']['median_ms']:.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
