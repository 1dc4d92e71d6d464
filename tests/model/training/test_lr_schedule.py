"""The learning-rate schedule against its closed form: one exponential decay over the run."""

import math

import pytest
import torch

from visnerf.config import TrainConfig
from visnerf.testing import make_noise_scene, make_tiny_field
from visnerf.training.trainer import Trainer

UPSAMPLE_AT = (0.2, 0.5)


def _trainer(iterations: int | None = 100, time_budget_s: float | None = None) -> Trainer:
    field, _ = make_tiny_field([("t", [0.0, 1.0])], seed=1, resolution=8)
    cfg = TrainConfig(iterations=iterations, time_budget_s=time_budget_s, resolution_init=8, resolution_final=12,
                      upsample_at=UPSAMPLE_AT, occupancy_at=(), carve=False, lr_decay_ratio=0.1)
    return Trainer(make_noise_scene(), None, cfg, torch.device("cpu"), init_field=field)


@pytest.mark.parametrize(("iteration", "upsamples_done", "expected"), [
    (0, 0, 1.0),
    (10, 0, 0.1 ** 0.1),
    (30, 1, 0.1 ** 0.3),
    (50, 2, 0.1 ** 0.5),
    (100, 2, 0.1),
    (150, 2, 0.1),  # past the end: held at the end's value
])
def test_scale_is_the_closed_form(iteration: int, upsamples_done: int, expected: float) -> None:
    trainer = _trainer()
    trainer.state.iteration, trainer.state.upsamples_done = iteration, upsamples_done
    assert math.isclose(trainer.lr_scale(), expected, rel_tol=1e-12), iteration


def test_a_step_sets_both_groups() -> None:
    trainer = _trainer()
    trainer.state.iteration = 19
    trainer.train_step()
    factors, networks = trainer.optimizer.param_groups
    scale = 0.1 ** 0.19
    assert math.isclose(factors["lr"], trainer.cfg.lr_factors * scale, rel_tol=1e-12)
    assert math.isclose(networks["lr"], trainer.cfg.lr_networks * scale, rel_tol=1e-12)


def test_an_upsample_keeps_the_decayed_rate() -> None:
    trainer = _trainer()
    trainer.state.iteration = 20
    trainer._milestones()
    assert trainer.state.upsamples_done == 1
    assert math.isclose(trainer.optimizer.param_groups[0]["lr"], trainer.cfg.lr_factors * 0.1 ** 0.2, rel_tol=1e-12)


def test_a_budgeted_run_follows_its_clock_past_any_step_count() -> None:
    """Under a time budget with no step limit, progress is the clock's alone: a fast machine's
    40,000 steps in a fifth of the budget are a fifth of the run, and the run goes on."""
    trainer = _trainer(iterations=None, time_budget_s=600.0)
    trainer.state.iteration, trainer.state.train_seconds = 40_000, 120.0
    assert math.isclose(trainer.progress(), 0.2, rel_tol=1e-12)
    assert trainer._go_on(None)
    trainer.state.train_seconds = 600.0
    assert not trainer._go_on(None)


def test_with_both_limits_the_further_along_sets_the_progress() -> None:
    trainer = _trainer(iterations=1000, time_budget_s=600.0)
    trainer.state.iteration, trainer.state.train_seconds = 500, 60.0
    assert math.isclose(trainer.progress(), 0.5, rel_tol=1e-12)
    trainer.state.iteration, trainer.state.train_seconds = 100, 300.0
    assert math.isclose(trainer.progress(), 0.5, rel_tol=1e-12)
