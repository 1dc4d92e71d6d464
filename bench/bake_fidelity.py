"""Bakes of the bundled scenes against the models' own full frames: PSNR of frames drawn from a
bake (``visnerf render --bake``'s renderer) on views of the scene's test path, at the path's
parameter values (between training values, a bake each) and at the default setting; seconds a
bake, MB a bake file.

    .venv/bin/python bench/bake_fidelity.py            # all bundled scenes, 24 views of 181
    .venv/bin/python bench/bake_fidelity.py --views 181 --size 256
    .venv/bin/python bench/bake_fidelity.py --truth vortex_tf1=data/gt_vortex_tf1   # and ground truth

``--truth SCENE=DIR``: a dataset of that scene (``visnerf make-scene SCENE --out DIR --views 1
--test-views 24``); its test frames are drawn by the model and by a bake of each frame's setting,
both scored against the truth. Writes bench/results/bake_fidelity.{json,md}.
"""

import visnerf  # noqa: F401  (before torch: the OpenMP wait policy)

# isort: split
import argparse
import math
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from bench_common import RESULTS, ROOT, evenly_spaced, load_average, machine_record, markdown_header, write_results

from visnerf.bake.bake_file import bake_bytes
from visnerf.bake.bake_render import DenseBake, render_bake
from visnerf.bake.baking import content_hash
from visnerf.bake.scene_bake import bake_scene
from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.data.datasets import load_dataset
from visnerf.inference import SceneRenderer, load_scene
from visnerf.scenes.protocol import path_angles, path_params


@dataclass(frozen=True)
class _Axis:
    """A checkpoint's axis as ``scenes.protocol`` reads one."""

    training: tuple[float, ...]

    def values(self) -> list[float]:
        return list(self.training)

    @property
    def count(self) -> int:
        return len(self.training)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(((a.astype(np.float64) - b.astype(np.float64)) ** 2).mean())
    return 10.0 * math.log10(255.0**2 / mse) if mse > 0 else float("inf")


def measure(scene: SceneRenderer, checkpoint_hash: str, views: list[int], size: int) -> dict:
    cam = scene.info.camera
    angles = path_angles(181)
    axes = tuple(_Axis(tuple(a.values)) for a in scene.info.params)
    values = path_params(axes, 181) if axes else [() for _ in range(181)]
    names = [a.name for a in scene.info.params]
    fov, view_height = cam.get("fov_deg"), cam.get("view_height")
    intrinsics = (Intrinsics.from_fov(size, size, math.radians(fov)) if fov is not None
                  else Intrinsics.from_view_height(size, size, float(view_height)))
    default = bake_scene(scene, {}, checkpoint_hash=checkpoint_hash)
    dense_default = DenseBake.of(default)
    between, at_default, seconds, mb = [], [], [], []
    for i in views:
        az, el = angles[i]
        c2w = orbit_c2w(az, el, cam["distance"])
        c2w_t = torch.tensor(c2w, dtype=torch.float32)
        params = dict(zip(names, values[i], strict=True))
        t0 = time.perf_counter()
        bake = bake_scene(scene, params, checkpoint_hash=checkpoint_hash)
        seconds.append(time.perf_counter() - t0)
        mb.append(len(bake_bytes(bake)) / 1e6)
        model = scene.render(c2w, fov, size, size, params, "full", view_height=view_height)
        between.append(psnr(render_bake(DenseBake.of(bake), c2w_t, intrinsics), model))
        model = scene.render(c2w, fov, size, size, {}, "full", view_height=view_height)
        at_default.append(psnr(render_bake(dense_default, c2w_t, intrinsics), model))
    return {
        "shading": default.header.shading, "grid": list(default.header.grid),
        "colour": default.header.source.get("sh_degree", ""),
        "between_psnr_median": statistics.median(between), "between_psnr_worst": min(between),
        "default_psnr_median": statistics.median(at_default), "default_psnr_worst": min(at_default),
        "bake_seconds_median": statistics.median(seconds), "bake_mb_median": statistics.median(mb),
        "bake_mb_max": max(mb),
    }


def against_truth(scene: SceneRenderer, folder: Path) -> dict:
    """Median PSNR against a dataset's test frames of the model's full frames and of frames drawn
    from a bake of each frame's setting, at the frames' own cameras and size."""
    frames = load_dataset(folder, "test")
    names = [a.name for a in scene.info.params]
    k = frames.intrinsics
    model_db, bake_db = [], []
    for i in range(frames.c2w.shape[0]):
        params = dict(zip(names, frames.params[i].tolist(), strict=True))
        c2w = frames.c2w[i].double().numpy()
        lens = (None, k.view_height) if k.orthographic else (k.fov_x_deg, None)
        truth = frames.images[i].numpy()
        if truth.dtype != np.uint8:
            truth = (truth.clip(0, 1) * 255.0 + 0.5).astype(np.uint8)
        model = scene.render(c2w, lens[0], k.width, k.height, params, "full", view_height=lens[1])
        bake = bake_scene(scene, params)
        local = render_bake(DenseBake.of(bake), torch.tensor(c2w, dtype=torch.float32), k)
        model_db.append(psnr(model, truth[..., :3]))
        bake_db.append(psnr(local, truth[..., :3]))
    return {"frames": len(model_db), "model_psnr_median": statistics.median(model_db),
            "bake_psnr_median": statistics.median(bake_db),
            "loss_db_median": statistics.median(m - b for m, b in zip(model_db, bake_db, strict=True))}


def write_markdown(path: Path, record: dict) -> None:
    lines = markdown_header("Bakes against the models' own frames", record)
    lines += ["", f"{record['views']} views of each scene's 181-view test path at {record['size']}x{record['size']}: "
              "PSNR of the frame drawn from the bake against the model's full frame, at the path's parameter "
              "values (a bake each, between training values) and at the default setting.", "",
              "| scene | shading | grid | between: median / worst dB | default: median / worst dB | "
              "bake s (median) | MB median / max |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, r in record["scenes"].items():
        lines.append(f"| {name} | {r['shading']} | {'x'.join(map(str, r['grid']))} | "
                     f"{r['between_psnr_median']:.2f} / {r['between_psnr_worst']:.2f} | "
                     f"{r['default_psnr_median']:.2f} / {r['default_psnr_worst']:.2f} | "
                     f"{r['bake_seconds_median']:.2f} | {r['bake_mb_median']:.2f} / {r['bake_mb_max']:.2f} |")
    truth = {n: r["truth"] for n, r in record["scenes"].items() if "truth" in r}
    if truth:
        lines += ["", "Against ground truth (the test frames of a dataset of the scene, their own cameras and size):", "",
                  "| scene | frames | model dB (median) | bake dB (median) | bake below the model, median dB |",
                  "| --- | --- | --- | --- | --- |"]
        lines += [f"| {n} | {t['frames']} | {t['model_psnr_median']:.2f} | {t['bake_psnr_median']:.2f} | "
                  f"{t['loss_db_median']:.2f} |" for n, t in truth.items()]
    lines += ["", "Colour fits chosen:", ""]
    lines += [f"- {name}: {r['colour']}" for name, r in record["scenes"].items()]
    path.write_text("\n".join(lines) + "\n")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=24, help="views of the 181-view test path (evenly spread)")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--scenes", nargs="*", default=None, help="bundled checkpoints by name (default: all)")
    ap.add_argument("--truth", action="append", default=[], metavar="SCENE=DIR",
                    help="a dataset of a bundled scene whose test frames both are scored against")
    args = ap.parse_args()
    paths = sorted((ROOT / "checkpoints").glob("*.safetensors"))
    if args.scenes:
        paths = [p for p in paths if p.stem in args.scenes]
    record = {**machine_record(), "command": " ".join(["bench/bake_fidelity.py", *sys.argv[1:]]),
              "views": args.views, "size": args.size, "load_average_1min": {"before": load_average()}, "scenes": {}}
    views = evenly_spaced(181, args.views)
    truths = {name: Path(folder) for name, _, folder in (t.partition("=") for t in args.truth)}
    for path in paths:
        scene = load_scene(path)
        record["scenes"][path.stem] = measure(scene, content_hash(path.read_bytes()), views, args.size)
        if path.stem in truths:
            record["scenes"][path.stem]["truth"] = against_truth(scene, truths[path.stem])
        print(path.stem, record["scenes"][path.stem], file=sys.stderr, flush=True)
    record["load_average_1min"]["after"] = load_average()
    write_results(RESULTS, "bake_fidelity", record, write_markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
