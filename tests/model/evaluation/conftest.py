"""A tiny K=2 dataset whose ground truth is a tiny checkpoint's own render plus noise, and its log."""

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from visnerf.data.cameras import orbit_c2w
from visnerf.inference import load_scene
from visnerf.scenes.protocol import ParamAxis, path_params
from visnerf.testing import make_tiny_checkpoint

SIZE = 16
AXES = [("a", [0.0, 1.0]), ("b", [0.0, 0.5, 1.0])]


def write_split(folder: Path, split: str, ckpt: Path, params: list[tuple[float, ...]], noise: float = 0.02) -> None:
    """Render the checkpoint at ``params`` along an orbit, add noise, write images and transforms."""
    scene = load_scene(ckpt, torch.device("cpu"))
    rng = np.random.default_rng(0)
    (folder / split).mkdir(parents=True, exist_ok=True)
    frames = []
    for i, values in enumerate(params):
        c2w = orbit_c2w(-60.0 + 120.0 * i / max(len(params) - 1, 1), 20.0, 2.5)
        img = scene.render(c2w, 30.0, SIZE, SIZE, dict(zip(("a", "b"), values, strict=True)))
        noisy = np.clip(img.astype(np.float64) / 255.0 + rng.normal(0.0, noise, img.shape), 0.0, 1.0)
        Image.fromarray((noisy * 255.0 + 0.5).astype(np.uint8)).save(folder / split / f"r_{i}.png")
        frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist(), "params": list(values)})
    doc = {"camera_angle_x": math.radians(30.0), "param_names": ["a", "b"], "white_background": True,
           "frames": frames}
    (folder / f"transforms_{split}.json").write_text(json.dumps(doc))


def eval_path() -> list[tuple[float, ...]]:
    """Two frames at training values (camera only moving), then the paper's path between them."""
    axes = (ParamAxis("a", 0.0, 1.0, 2), ParamAxis("b", 0.0, 1.0, 3))
    return [(1.0, 0.5), (1.0, 0.5), *path_params(axes, 10)]




@pytest.fixture(scope="session")
def tiny_eval(tmp_path_factory) -> tuple[Path, Path]:
    """(checkpoint with its training log beside it, dataset folder with a test split)."""
    root = tmp_path_factory.mktemp("eval")
    ckpt = make_tiny_checkpoint(root / "tiny.safetensors", AXES)
    data = root / "data"
    write_split(data, "test", ckpt, eval_path())
    rows = [{"iteration": 100 * (i + 1), "train_seconds": 30.0 * (i + 1), "wall_seconds": 32.0 * (i + 1),
             "train_psnr": 15.0 + i, "resolution": 8, "val_psnr": 14.0 + 0.8 * i, "val_ssim": 0.5 + 0.05 * i,
             "val_ms_per_frame": 5.0} for i in range(4)]
    with (root / "tiny.log.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return ckpt, data
