"""Occupancy rebuilds of trained fields: the union over settings with the cells already found
occupied skipped (``build_occupancy``) against every cell evaluated at every setting.

Training rebuilds its occupancy grid at milestones (``TrainConfig.occupancy_at``,
``occupancy_refine_at``, the end): the union over all training settings (up to
``occupancy_max_settings``) of the cells where the density is visible. For each bundled checkpoint
this times both ways on the checkpoint's field, the settings its training would use (every
combination of its training values, up to the cap) and its occupancy resolution, in two cases:

- refine: only the cells of the checkpoint's own grid are evaluated (``Trainer.refine_occupancy``);
- box: every cell of the box (``Trainer.update_occupancy`` without a carved hull).

Checks that both ways give the same grid, and writes bench/results/occupancy_build.json and .md.

    .venv/bin/python bench/occupancy_build.py
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from bench_common import RESULTS, machine_record, write_results

from visnerf.checkpoint import load_checkpoint
from visnerf.config import TrainConfig
from visnerf.rendering.occupancy import build_occupancy, cell_centres, cell_offsets, parameter_settings
from visnerf.representation.field import VisNerfField
from visnerf.representation.frame_field import FrameField
from visnerf.runtime import bf16_native

SCENES = ("plume_time", "tangle_iso", "vortex_tf1", "cosmo_sim")


@torch.no_grad()
def every_cell_every_setting(field: VisNerfField, res: tuple[int, int, int], settings: torch.Tensor, step: float,
                             threshold: float, candidates: torch.Tensor | None, chunk: int = 65536) -> torch.Tensor:
    """The rebuild before cells were skipped: each setting evaluates every candidate cell."""
    pts = cell_centres(field.aabb, res).reshape(-1, 3)  # [x*y*z, 3]
    cand = torch.arange(pts.shape[0]) if candidates is None else candidates.reshape(-1).nonzero()[:, 0]
    pts = pts[cand]
    offsets = cell_offsets(res, field.aabb[1] - field.aabb[0], 2)  # [8, 3]
    per_chunk = max(1, chunk // offsets.shape[0])
    occupied = torch.zeros(pts.shape[0], dtype=torch.bool)
    for setting in settings:
        q_d, q_a = field.param_features(setting[None])
        frame = FrameField(field, q_d, q_a, torch.bfloat16 if bf16_native(pts.device) else torch.float32)
        for start in range(0, pts.shape[0], per_chunk):
            part = (pts[start:start + per_chunk, None, :] + offsets[None]).reshape(-1, 3)
            sigma = frame.density(part).reshape(-1, offsets.shape[0]).amax(dim=1)
            occupied[start:start + per_chunk] |= -torch.expm1(-sigma * step) > threshold
    full = torch.zeros(cell_centres(field.aabb, res).shape[:3].numel(), dtype=torch.bool)
    full[cand] = occupied
    return full.reshape(res)


def measure(path: Path, repeats: int) -> list[dict]:
    field, meta = load_checkpoint(path, torch.device("cpu"))
    field.eval()
    knots = [torch.tensor([axis.normalize(v) for v in axis.values]) for axis in meta.param_axes]
    settings = parameter_settings(knots, TrainConfig.occupancy_max_settings, torch.Generator().manual_seed(0))
    trained = field.occupancy
    res = tuple(trained.shape) if trained is not None else (TrainConfig.occupancy_resolution,) * 3
    step = field.voxel_size() * meta.render.step_ratio
    threshold = meta.render.occupancy_threshold
    rows = []
    for case, candidates in (("refine", trained), ("box", None)):
        skipped_s, every_s = [], []
        for _ in range(repeats):  # alternated, so that both share the machine's noise
            t0 = time.perf_counter()
            skipped = build_occupancy(field, res, settings, step, threshold, candidates, dilation=0)
            skipped_s.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            every = every_cell_every_setting(field, res, settings, step, threshold, candidates)
            every_s.append(time.perf_counter() - t0)
        if not torch.equal(skipped, every):
            raise SystemExit(f"{path.name} {case}: the two rebuilds differ in {int((skipped ^ every).sum())} cells")
        rows.append({
            "scene": path.stem, "case": case, "settings": int(settings.shape[0]), "resolution": list(res),
            "cells_evaluated": int(candidates.sum()) if candidates is not None else int(torch.tensor(res).prod()),
            "cells_occupied": int(skipped.sum()), "skipping_s": statistics.median(skipped_s),
            "every_cell_s": statistics.median(every_s), "same_grid": True,
        })
        print(rows[-1], file=sys.stderr, flush=True)
    return rows


def write_markdown(path: Path, record: dict) -> None:
    lines = [
        "# Occupancy rebuilds: cells found occupied skipped at later settings",
        "",
        f"Machine: {record['machine']}; torch {record['torch']}, {record['torch_threads']} threads; {record['date']}.",
        "",
        "`.venv/bin/python bench/occupancy_build.py`: each bundled checkpoint's field, the settings its training "
        "rebuilds over (every combination of its training values, at most `occupancy_max_settings`), "
        f"its occupancy resolution; median of {record['repeats']} alternated runs of each way. *refine*: only "
        "the cells of the checkpoint's grid are evaluated, as training's refinements and its last rebuild do; "
        "*box*: every cell, as the first rebuild does without a carved hull. Both ways give the same grid.",
        "",
        "| scene | case | settings | cells evaluated | occupied | every cell at every setting (s) | skipping cells found occupied (s) | ratio |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in record["rows"]:
        ratio = r["every_cell_s"] / max(r["skipping_s"], 1e-9)
        lines.append(f"| {r['scene']} | {r['case']} | {r['settings']} | {r['cells_evaluated']:,} | "
                     f"{r['cells_occupied']:,} | {r['every_cell_s']:.2f} | {r['skipping_s']:.2f} | {ratio:.1f}x |")
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoints", nargs="+", default=[f"checkpoints/{s}.safetensors" for s in SCENES])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rows = [row for ckpt in args.checkpoints for row in measure(Path(ckpt), args.repeats)]
    record = {**machine_record(), "repeats": args.repeats, "rows": rows}
    write_results(Path(args.results), "occupancy_build", record, write_markdown)


if __name__ == "__main__":
    main()
