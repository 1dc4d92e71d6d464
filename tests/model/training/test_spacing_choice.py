"""Where a training run chooses its checkpoint's full-quality spacing: on the held-out frames, or on
the training frames where nothing is held out (``Trainer.run``, ``evaluation.spacing``)."""

import pytest
import torch

import visnerf.training.trainer as trainer_module
from visnerf.config import RenderConfig, TrainConfig
from visnerf.data.scene import SceneData
from visnerf.evaluation.spacing import CANDIDATES
from visnerf.testing import make_noise_scene, make_tiny_field
from visnerf.training.trainer import Trainer


def _run(val: SceneData | None, choose: bool, monkeypatch: pytest.MonkeyPatch) -> tuple[Trainer, SceneData, list]:
    """A few steps on a noise scene, with ``choose_full_spacing`` spied on: (trainer, train scene,
    the scenes the choice was made on)."""
    measured: list[SceneData] = []
    real = trainer_module.choose_full_spacing

    def spy(field, scene, *args, **kwargs):
        measured.append(scene)
        return real(field, scene, *args, **kwargs)

    monkeypatch.setattr(trainer_module, "choose_full_spacing", spy)
    field, _ = make_tiny_field([("t", [0.0, 1.0])], seed=1, resolution=8)
    cfg = TrainConfig(iterations=4, resolution_init=8, resolution_final=8, upsample_at=(), occupancy_at=(),
                      carve=False, validate_max_images=2, choose_full_spacing=choose)
    train = make_noise_scene()
    trainer = Trainer(train, val, cfg, torch.device("cpu"), init_field=field)
    trainer.run(progress_bar=False)
    return trainer, train, measured


def test_nothing_held_out_chooses_on_the_training_frames(monkeypatch: pytest.MonkeyPatch) -> None:
    trainer, train, measured = _run(None, True, monkeypatch)
    assert len(measured) == 1 and measured[0] is train
    assert trainer.spacing_note is not None and trainer.spacing_note.endswith(", training frames (none held out)")
    assert trainer.spacing_note.startswith(f"full-quality spacing {trainer.render_cfg.full_step_ratio:g} voxel")
    assert trainer.render_cfg.full_step_ratio in (*CANDIDATES, 0.5)


def test_held_out_frames_are_chosen_on_when_there_are_some(monkeypatch: pytest.MonkeyPatch) -> None:
    val = make_noise_scene(n_views=4)
    trainer, train, measured = _run(val, True, monkeypatch)
    assert len(measured) == 1 and measured[0] is val and measured[0] is not train
    assert trainer.spacing_note is not None and "training frames" not in trainer.spacing_note


def test_the_choice_switched_off_keeps_the_configured_spacing(monkeypatch: pytest.MonkeyPatch) -> None:
    trainer, _, measured = _run(None, False, monkeypatch)
    assert measured == [] and trainer.spacing_note is None
    assert trainer.render_cfg.full_step_ratio == RenderConfig().full_step_ratio  # what such a run kept
