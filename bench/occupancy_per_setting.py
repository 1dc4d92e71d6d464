"""Does an occupancy grid per parameter setting pay, against the checkpoint's union grid?

The renderer skips empty space with one grid: the union over the parameter space of the cells
where any training setting has visible density (stored in the checkpoint). A grid built for the
frame's own parameter tuple could only skip more. For each checkpoint and each of its held-out
views (as bench/render_speed.py picks them), this builds that grid at the frame's parameters as
the server's cache does (``rendering.setting_occupancy.build_setting_grid``: density at
``--samples-per-axis``^3 points of each of the union's occupied cells, alpha at the full-quality
step above the checkpoint's occupancy threshold, dilated by one cell, intersected with the union),
then renders the frame with each grid, interleaved, and records:

- the occupied fraction of each grid and the density samples each frame evaluates;
- ms per frame with each grid (the build excluded), and the build's ms;
- the PSNR between the two frames (the per-setting grid must not cut visible content).

    python bench/occupancy_per_setting.py --threads 1 --views 6

Writes bench/results/occupancy_per_setting.{json,md}.
"""

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from bench_common import RESULTS, load_average, machine_record, markdown_header, write_json
from render_speed import default_cases, load_views, parse_case

from visnerf.inference import load_scene
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.renderer import RenderSettings, render_image
from visnerf.rendering.setting_occupancy import build_setting_grid
from visnerf.representation.frame_field import FrameField, SampleTaps
from visnerf.runtime import configure


class Counting:
    """Counts the density samples a render evaluates."""

    def __init__(self) -> None:
        self.samples = 0
        self._orig = FrameField.density_at

    def __enter__(self) -> "Counting":
        counter = self

        def density_at(frame: FrameField, samples: SampleTaps) -> torch.Tensor:
            counter.samples += len(samples)
            return counter._orig(frame, samples)

        FrameField.density_at = density_at  # type: ignore[method-assign]
        return self

    def __exit__(self, *exc: object) -> None:
        FrameField.density_at = self._orig  # type: ignore[method-assign]


def measure(case, views_count: int, size: int, samples_per_axis: int) -> dict:
    scene = load_scene(case.checkpoint)
    field, meta = scene.field, scene.meta
    settings = RenderSettings.from_meta(meta, "full")
    step = field.voxel_size() * settings.step_ratio
    union = field.occupancy.clone()
    views = load_views(scene, Path(case.data), views_count)
    cam = views.intrinsics.scaled(size, size)
    rows = []
    with torch.inference_mode():
        render_image(field, views.c2w[0], cam, views.params[0], settings)  # warm-up
        for v in range(views.c2w.shape[0]):
            params = views.params[v]
            t0 = time.perf_counter()
            own_grid = build_setting_grid(field, params, step, meta.render.occupancy_threshold, samples_per_axis)
            own = EmptySpace.of(own_grid, field.aabb)
            build_ms = 1000 * (time.perf_counter() - t0)
            out = {}
            for name, space, grid in (("union", None, union), ("setting", own, own_grid)):
                with Counting() as count:
                    t0 = time.perf_counter()
                    img = render_image(field, views.c2w[v], cam, params, settings, space)
                    ms = 1000 * (time.perf_counter() - t0)
                out[name] = (img, ms, count.samples, float(grid.float().mean()))
            mse = float(((out["union"][0] - out["setting"][0]) ** 2).mean())
            rows.append({
                "view": views.frame_indices[v], "build_ms": build_ms,
                "union_fraction": out["union"][3], "setting_fraction": out["setting"][3],
                "union_samples": out["union"][2], "setting_samples": out["setting"][2],
                "union_ms": out["union"][1], "setting_ms": out["setting"][1],
                "psnr_setting_vs_union": math.inf if mse == 0 else 10 * math.log10(1 / mse),
            })  # fmt: skip
    med = {k: float(np.median([r[k] for r in rows])) for k in rows[0] if k not in ("view", "psnr_setting_vs_union")}
    return {"name": case.name, "checkpoint": str(case.checkpoint), "size": size, "views": rows, "median": med,
            "min_psnr_setting_vs_union": float(min(r["psnr_setting_vs_union"] for r in rows))}


def write_markdown(path: Path, record: dict) -> None:
    lines = [
        *markdown_header("Occupancy grid per parameter setting against the union grid", record),
        "",
        "Medians over the held-out views of bench/render_speed.py. Samples: density evaluations per frame.",
        "",
        "| checkpoint | size | occupied: union / own | samples: union / own | ms: union / own | build ms | "
        "lowest PSNR own vs union |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for c in record["cases"]:
        m = c["median"]
        lines.append(
            f"| {c['name']} | {c['size']} | {m['union_fraction']:.3f} / {m['setting_fraction']:.3f} | "
            f"{m['union_samples']:.0f} / {m['setting_samples']:.0f} | {m['union_ms']:.0f} / {m['setting_ms']:.0f} | "
            f"{m['build_ms']:.0f} | {c['min_psnr_setting_vs_union']:.1f} dB |")
    lines += ["", "A per-setting grid pays only where it removes more render time than its build costs, "
              "amortised over the frames drawn at one parameter tuple.", ""]
    path.write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoints", nargs="+", default=None, metavar="PATH[=DATASET]")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--samples-per-axis", type=int, default=2, help="density samples per cell and axis (default 2)")
    ap.add_argument("--out-dir", default=str(RESULTS))
    args = ap.parse_args(argv)
    configure(args.threads)
    cases = tuple(parse_case(s) for s in args.checkpoints) if args.checkpoints else default_cases()
    record = {"command": "python bench/occupancy_per_setting.py " + " ".join(sys.argv[1:]), **machine_record()}
    before = load_average()
    record["cases"] = []
    for case in cases:
        if not (Path(case.checkpoint).is_file() and Path(case.data).is_dir()):
            print(f"{case.name}: skipped, {case.checkpoint} or {case.data} is missing", flush=True)
            continue
        record["cases"].append(measure(case, args.views, args.size, args.samples_per_axis))
        print(f"{case.name}: {record['cases'][-1]['median']}", flush=True)
    record["load_average_1min"] = {"before": before, "after": load_average()}
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "occupancy_per_setting.json", record)
    write_markdown(out / "occupancy_per_setting.md", record)
    return 0


if __name__ == "__main__":
    sys.exit(main())

