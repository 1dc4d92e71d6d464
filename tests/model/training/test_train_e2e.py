"""A tiny synthetic scene trained end to end; the PSNR is measured on views it never saw."""

import numpy as np
import pytest
import torch

from visnerf.evaluation.spacing import CANDIDATES
from visnerf.inference import load_scene
from visnerf.training.trainer import Trainer


@pytest.mark.slow
def test_tiny_scene_trains_and_generalises_to_unseen_views(tmp_path, tiny_plume_run):
    train, val = tiny_plume_run.train, tiny_plume_run.val
    trainer = Trainer(train, val, tiny_plume_run.cfg, torch.device("cpu"))
    log = trainer.run(progress_bar=False)
    ckpt = trainer.save(tmp_path / "plume.safetensors")
    print("final log row:", log[-1])
    assert log[-1]["val_psnr"] > tiny_plume_run.min_held_out_psnr, log
    assert (tmp_path / "plume.log.csv").exists()
    loaded = load_scene(ckpt)
    # The full-quality spacing was chosen on the held-out frames (evaluation.spacing).
    assert "exhaustive" in (loaded.meta.provenance.full_spacing or "")
    assert trainer.render_cfg.full_step_ratio in (*CANDIDATES, 0.5)
    assert loaded.meta.render.full_step_ratio == trainer.render_cfg.full_step_ratio
    names = [a.name for a in loaded.info.params]
    img = loaded.render(val.c2w[0].double().numpy(), val.intrinsics.fov_x_deg, 32, 32,
                        dict(zip(names, val.params[0].tolist(), strict=True)))
    gt = val.images[0].numpy()
    assert img.shape == gt.shape and np.isfinite(img).all()
