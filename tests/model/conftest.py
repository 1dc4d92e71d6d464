"""A tiny time-varying scene and the short training run that the end-to-end tests share."""

import subprocess
import sys
from dataclasses import dataclass

import pytest
import torch

from visnerf.config import HoldoutConfig, TrainConfig
from visnerf.data.datasets import load_dataset
from visnerf.data.holdout import split_holdout
from visnerf.data.scene import SceneData


@dataclass(frozen=True)
class TinyRun:
    train: SceneData
    val: SceneData
    cfg: TrainConfig
    min_held_out_psnr: float
    """A floor, not the typical value (the run prints its final log row with `pytest -s`)."""


@pytest.fixture
def one_torch_thread():
    """Small renders on one thread: two threads oversubscribe a shared CPU (10x slower there)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def tiny_plume_run(tmp_path) -> TinyRun:
    """``plume_time`` at 32x32 with three views held out, and 300 iterations of a small grid."""
    data = tmp_path / "plume"
    subprocess.run([sys.executable, "-m", "visnerf.cli", "make-scene", "plume_time", "--out", str(data),
                    "--res", "32", "--test-views", "4", "--quiet"], check=True)
    train, val = split_holdout(load_dataset(data), HoldoutConfig(views=(3, 11, 25)))
    assert val is not None
    cfg = TrainConfig(iterations=300, batch_rays=1024, resolution_init=24, resolution_final=40,
                      upsample_at=(0.3, 0.5), occupancy_at=(0.25, 0.6), occupancy_min_iterations=50,
                      l1_switch_iteration=150, validate_every_s=1e9, validate_max_images=6)
    return TinyRun(train, val, cfg, min_held_out_psnr=17.0)
