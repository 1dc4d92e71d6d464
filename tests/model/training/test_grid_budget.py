"""The final grid a time budget can fill: closed forms, bounds, and the schedule that applies it."""

import math

import pytest
import torch

from visnerf.config import TrainConfig
from visnerf.testing import make_noise_scene, make_tiny_field
from visnerf.training.grid_budget import GridBudget
from visnerf.training.trainer import Trainer


@pytest.mark.parametrize(("rate", "now", "left", "per_voxel"), [
    (30_000.0, 64.0, 1100.0, 4.0), (12_000.0, 48.0, 3300.0, 14.0), (500.0, 8.0, 90.0, 1.0)])
def test_with_nothing_seen_the_grid_is_the_fourth_root_of_the_rate(rate, now, left, per_voxel):
    """``n^3 * R = rate * (now / n) * left`` gives ``n = (rate * now * left / R)^(1/4)``."""
    budget = GridBudget(0.0, rate, now, left)
    expected = (rate * now * left / per_voxel) ** 0.25
    assert expected > now
    assert math.isclose(budget.largest_grid(per_voxel, 1e6), expected, rel_tol=1e-9)


def test_rays_seen_count_and_the_grid_holds_at_most_the_rays_over_r():
    budget = GridBudget(5e6, 20_000.0, 64.0, 1000.0)
    n = budget.largest_grid(4.0, 1e6)
    assert math.isclose(n**3 * 4.0, budget.rays_at(n), rel_tol=1e-9)
    assert n > GridBudget(0.0, 20_000.0, 64.0, 1000.0).largest_grid(4.0, 1e6)


def test_the_grid_stays_within_the_grid_reached_and_the_ceiling():
    assert GridBudget(0.0, 1e9, 64.0, 3600.0).largest_grid(4.0, 200.0) == 200.0  # the footprint's grid
    assert GridBudget(0.0, 10.0, 64.0, 1.0).largest_grid(4.0, 200.0) == 64.0  # never below what it holds
    assert GridBudget(0.0, 10.0, 64.0, -5.0).largest_grid(4.0, 200.0) == 64.0  # past the budget


@pytest.mark.parametrize("bad", [
    dict(per_voxel=0.0), dict(per_voxel=math.nan), dict(rate=math.inf), dict(rate=-1.0), dict(now=0.0), dict(seen=math.nan)])
def test_bad_measures_are_refused_naming_them(bad):
    values = dict(seen=0.0, rate=1e4, now=64.0, per_voxel=4.0) | bad
    with pytest.raises(ValueError, match="rays_per_voxel|grid budget"):
        GridBudget(values["seen"], values["rate"], values["now"], 100.0).largest_grid(values["per_voxel"], 200.0)


def _trainer(rays_per_voxel: float) -> Trainer:
    field, _ = make_tiny_field([("t", [0.0, 1.0])], seed=1, resolution=8)
    cfg = TrainConfig(time_budget_s=100.0, resolution_init=8, resolution_final=40, upsample_at=(0.1, 0.2),
                      occupancy_at=(), carve=False, batch_rays=64, rays_per_voxel=rays_per_voxel)
    trainer = Trainer(make_noise_scene(), None, cfg, torch.device("cpu"), init_field=field)
    trainer.recipe_choices = [{"name": "rays_per_voxel", "value": rays_per_voxel, "reason": "a time budget"}]
    return trainer


def _reach(trainer: Trainer, iteration: int, seconds: float) -> None:
    trainer.state.iteration, trainer.state.train_seconds = iteration, seconds
    trainer._milestones()


def test_the_schedule_grows_the_grid_to_what_the_budget_fills():
    """1000 steps of 64 rays in 10 s at 8 voxels a side: 6400 rays a second, 90 s left. The cut
    at the first upsampling is the budget's grid, the last upsampling reaches the one measured at
    the grid before, and the recipe's record says so."""
    trainer = _trainer(rays_per_voxel=8.0)
    _reach(trainer, 1000, 10.0)
    first = GridBudget(64_000.0, 6400.0, 8.0, 90.0).largest_grid(8.0, 40.0)
    assert math.isclose(trainer.state.final_grid, first, rel_tol=1e-12) and 8.0 < first < 40.0
    reached = math.prod(trainer.field.resolution) ** (1 / 3)
    assert 8.0 < reached < first
    assert (trainer.state.mark_iteration, trainer.state.mark_seconds) == (1000, 10.0)
    _reach(trainer, 1500, 20.0)  # 500 steps in 10 s at the grid reached
    second = GridBudget(96_000.0, 3200.0, reached, 80.0).largest_grid(8.0, 40.0)
    assert math.isclose(trainer.state.final_grid, second, rel_tol=1e-12)
    assert math.isclose(math.prod(trainer.field.resolution) ** (1 / 3), second, rel_tol=0.1)
    assert "at most" in trainer.recipe_choices[0]["reason"] and trainer.recipe_choices[0]["reason"].count("[at") == 1


def test_a_budget_too_small_for_any_growth_keeps_the_grid():
    trainer = _trainer(rays_per_voxel=1e6)
    before = trainer.field.resolution
    _reach(trainer, 100, 10.0)
    _reach(trainer, 110, 20.0)
    assert trainer.state.upsamples_done == 2 and trainer.field.resolution == before
    assert math.isclose(trainer.state.final_grid, 8.0, rel_tol=1e-12)


def test_without_the_rule_the_grid_is_the_configured_one():
    trainer = _trainer(rays_per_voxel=0.0)
    _reach(trainer, 100, 10.0)
    _reach(trainer, 110, 20.0)
    assert trainer.state.final_grid == 0.0
    assert math.isclose(math.prod(trainer.field.resolution) ** (1 / 3), 40.0, rel_tol=0.1)
