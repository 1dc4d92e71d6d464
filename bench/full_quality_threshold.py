"""Full-quality frames' colour threshold: a weight per sample against a weight per voxel of spacing.

Full-quality frames decode colour only for samples above a weight and give the rest of the ray's
weight the mean colour of its decoded samples. For each checkpoint, on ``--frames`` frames of its
test path, renders the exhaustive frames (every sample, float32, within the model's grid) and the
full-quality frames at 1.5, 1 and 0.5 voxel with the old threshold (3e-3 a sample), the new one
(``RenderConfig.full_weight_threshold_per_voxel`` a voxel) and none to speak of (1e-4 a sample):
mean PSNR against the ground truth and against the exhaustive frames, median ms of a frame.

    .venv/bin/python bench/full_quality_threshold.py --scenes cosmo_sim plume_time vortex_tf1
"""

import argparse
import functools
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from bench_common import RESULTS, ROOT, cpu_description, write_json

from visnerf.checkpoint import load_checkpoint
from visnerf.config import RenderConfig
from visnerf.data.parsers.blender import load_dataset
from visnerf.evaluation.metrics import psnr
from visnerf.rendering.renderer import RenderSettings, render_image

RATIOS = (1.5, 1.0, 0.5)
PER_SAMPLE = {"3e-3 a sample (before)": 3e-3, "1e-4 a sample": 1e-4}


def render_frames(field, scene, params, idx, settings: RenderSettings) -> tuple[list[np.ndarray], float]:  # noqa: ANN001
    """The frames ``idx`` of ``scene`` and the median ms of one."""
    frames, ms = [], []
    with torch.inference_mode():
        for i in idx:
            t0 = time.perf_counter()
            frames.append(render_image(field, scene.c2w[i], scene.intrinsics, params[i], settings).clamp(0, 1).numpy())
            ms.append(1000 * (time.perf_counter() - t0))
    return frames, statistics.median(ms)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["cosmo_sim", "plume_time", "vortex_tf1"])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args()
    per_voxel = RenderConfig.full_weight_threshold_per_voxel
    rows = []
    for name in args.scenes:
        field, meta = load_checkpoint(ROOT / "checkpoints" / f"{name}.safetensors", torch.device("cpu"))
        field.eval()
        scene = load_dataset(ROOT / "data" / name, "test")
        idx = np.linspace(0, scene.n_frames - 1, args.frames).round().astype(int)
        params = scene.normalized_params()
        truth = [scene.images[i].numpy().astype(np.float32) / 255.0 for i in idx]

        run = functools.partial(render_frames, field, scene, params, idx)
        exhaustive = RenderSettings.from_config(meta.render, scene.background, "exhaustive")
        reference, _ = run(replace(exhaustive, use_occupancy=True))
        ref_psnr = float(np.mean([psnr(a, b) for a, b in zip(reference, truth, strict=True)]))
        full = RenderSettings.from_config(meta.render, scene.background, "full")
        for ratio in RATIOS:
            thresholds = {f"{per_voxel:g} a voxel (now)": per_voxel,
                          **{k: v / ratio for k, v in PER_SAMPLE.items()}}
            for label, threshold in thresholds.items():
                frames, ms = run(replace(full, step_ratio=ratio, weight_threshold_per_voxel=threshold))
                rows.append({
                    "scene": name, "voxel": ratio, "threshold": label, "exhaustive_psnr": ref_psnr,
                    "psnr": float(np.mean([psnr(a, b) for a, b in zip(frames, truth, strict=True)])),
                    "vs_exhaustive": float(np.mean([psnr(a, b) for a, b in zip(frames, reference, strict=True)])),
                    "ms": ms,
                })
                print(rows[-1], file=sys.stderr)
    record = {"command": "python bench/full_quality_threshold.py " + " ".join(sys.argv[1:]),
              "machine": f"{cpu_description()}, {torch.get_num_threads()} threads, torch {torch.__version__}",
              "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "frames": args.frames, "rows": rows}
    write_json(args.results / "full_quality_threshold.json", record)
    lines = ["# Full-quality colour threshold: per sample against per voxel of spacing", "",
             f"`{record['command']}`  ", f"{record['machine']}, {record['date']}; {args.frames} frames of each "
             "bundled checkpoint's test path at 128x128. dB against the ground truth (delta: minus the exhaustive "
             "frames'), dB from the exhaustive frames, median ms of a frame.", "",
             "| scene | voxel | threshold | dB (delta) | dB from exhaustive | ms |", "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {r['scene']} | {r['voxel']:g} | {r['threshold']} | {r['psnr']:.3f} ({r['psnr'] - r['exhaustive_psnr']:+.3f}) "
              f"| {r['vs_exhaustive']:.1f} | {r['ms']:.0f} |" for r in rows]
    (args.results / "full_quality_threshold.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
