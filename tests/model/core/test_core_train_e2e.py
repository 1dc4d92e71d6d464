"""A tiny synthetic scene trained end to end; the PSNR is measured on views it never saw."""

import subprocess
import sys

import numpy as np
import torch

from visnerf.config import HoldoutConfig, TrainConfig
from visnerf.data.holdout import split_holdout
from visnerf.data.parsers.blender import load_dataset
from visnerf.inference import load_scene
from visnerf.rendering.spacing import CANDIDATES
from visnerf.training.trainer import Trainer

# The run prints its final log row (held-out PSNR) with `pytest -s`; the bound is a floor, not the typical value.
MIN_HELD_OUT_PSNR = 17.0


def test_tiny_scene_trains_and_generalises_to_unseen_views(tmp_path):
    data = tmp_path / "plume"
    subprocess.run([sys.executable, "-m", "visnerf.cli", "make-scene", "plume_time", "--out", str(data),
                    "--res", "32", "--test-views", "4", "--quiet"], check=True)
    scene = load_dataset(data)
    train, val = split_holdout(scene, HoldoutConfig(views=(3, 11, 25)))
    cfg = TrainConfig(iterations=300, batch_rays=1024, resolution_init=24, resolution_final=40,
                      upsample_at=(0.3, 0.5), occupancy_at=(0.25, 0.6), occupancy_min_iterations=50, importance_from=2.0,
                      l1_switch_iteration=150, validate_every_s=1e9, validate_max_images=6)
    trainer = Trainer(train, val, cfg, torch.device("cpu"))
    log = trainer.run(progress_bar=False)
    ckpt = trainer.save(tmp_path / "plume.safetensors")
    print("final log row:", log[-1])
    assert log[-1]["val_psnr"] > MIN_HELD_OUT_PSNR, log
    assert (tmp_path / "plume.log.csv").exists()
    loaded = load_scene(ckpt)
    # The full-quality spacing was chosen on the held-out frames (rendering.spacing).
    assert "full_spacing" in loaded.meta.provenance and "exhaustive" in loaded.meta.provenance["full_spacing"]
    assert trainer.render_cfg.full_step_ratio in (*CANDIDATES, 0.5)
    assert loaded.meta.render.full_step_ratio == trainer.render_cfg.full_step_ratio
    names = [a.name for a in loaded.info.params]
    img = loaded.render(val.c2w[0].double().numpy(), val.intrinsics.fov_x_deg, 32, 32,
                        dict(zip(names, val.params[0].tolist(), strict=True)))
    gt = val.images[0].numpy()
    assert img.shape == gt.shape and np.isfinite(img).all()
