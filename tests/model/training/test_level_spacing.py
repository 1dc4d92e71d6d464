"""The bound on a level axis's band slopes against closed forms (nothing within the bound, the
squared excess of the log ratio beyond it, unchanged when the levels and the sharpness are scaled
inversely, nothing below three levels or without a level axis), its pull on a level that ran off,
and its place in a training step."""

import math

import pytest
import torch

from visnerf.config import TrainConfig
from visnerf.testing import make_noise_scene, make_tiny_field
from visnerf.training.regularizers import level_spacing
from visnerf.training.trainer import Trainer

RATIO = 4.0


def _level_field(levels: list[float], log_sharpness: float = 0.0):
    values = [0.1 * (i + 1) for i in range(len(levels))]
    field, _ = make_tiny_field([("isovalue", values)], seed=2, resolution=8, level_set_axis=0)
    with torch.no_grad():
        field.levels.table.copy_(torch.tensor(levels)[:, None])
        field.levels.log_sharpness.fill_(log_sharpness)
    return field


def _value(field, ratio: float = RATIO) -> float:
    return float(level_spacing(field, ratio).detach())


def test_bands_within_the_ratio_cost_nothing() -> None:
    assert _value(_level_field([-1.0, 0.0, 1.0])) == 0.0
    assert _value(_level_field([2.0, 1.5, 1.0, 0.5])) == 0.0  # decreasing levels
    assert _value(_level_field([0.0, 1.0, 4.0], log_sharpness=3.0)) == 0.0  # rises 3 times the one before


def test_bands_beyond_the_ratio_match_the_closed_form() -> None:
    # knots -1, 0, 1: slopes 1 and 20 per unit; sharpness e^0.5
    s = math.exp(0.5)
    excess = math.log1p(20.0 * s) - math.log1p(1.0 * s) - math.log(RATIO)
    assert excess > 0
    assert _value(_level_field([0.0, 1.0, 21.0], log_sharpness=0.5)) == pytest.approx(excess**2, rel=1e-5)
    # four levels (knots 2/3 apart): the mean over the two pairs of neighbouring bands, one within
    rises = [math.log1p(d / (2.0 / 3.0)) for d in (1.0, 30.0, 40.0)]
    expected = ((rises[1] - rises[0] - math.log(RATIO)) ** 2 + 0.0) / 2.0
    assert _value(_level_field([0.0, 1.0, 31.0, 71.0])) == pytest.approx(expected, rel=1e-5)


def test_scaling_the_levels_against_the_sharpness_changes_nothing() -> None:
    levels = (0.0, 0.03, 1.1, 1.5)
    base = _value(_level_field(list(levels), log_sharpness=3.0))
    scaled = _value(_level_field([10.0 * v for v in levels], log_sharpness=3.0 - math.log(10.0)))
    assert base > 1e-3
    assert scaled == pytest.approx(base, rel=1e-5)


def test_a_level_that_ran_off_is_pulled_back_through_the_table_only() -> None:
    field = _level_field([-113.0, -0.86, -0.25, 0.42, 1.07], log_sharpness=5.5)  # the failed run's table
    level_spacing(field, RATIO).backward()
    grad = field.levels.table.grad[:, 0]
    assert float(grad[0]) < 0  # descent raises the lowest level back toward its neighbours
    assert field.levels.log_sharpness.grad is None
    assert field.density_grid.plane_table.grad is None


def test_fewer_than_three_levels_or_no_level_axis_get_nothing() -> None:
    assert _value(_level_field([0.0, 5.0])) == 0.0
    field, _ = make_tiny_field([("isovalue", [0.1, 0.2, 0.3])], seed=2, resolution=8)
    assert _value(field) == 0.0


def test_a_ratio_of_one_or_less_is_refused() -> None:
    with pytest.raises(ValueError, match="max_ratio"):
        level_spacing(_level_field([0.0, 1.0, 2.0]), 1.0)
    with pytest.raises(ValueError, match="level_spacing_ratio"):
        TrainConfig(level_spacing_ratio=float("nan"))


def _step(values: list[float], weight: float) -> dict[str, float]:
    field, _ = make_tiny_field([("t", values)], seed=1, resolution=8, level_set_axis=0)
    with torch.no_grad():
        field.levels.table.copy_(torch.tensor([0.0, 0.01, 5.0])[: len(values), None])  # bands 500 times apart
    cfg = TrainConfig(iterations=10, resolution_init=8, resolution_final=8, occupancy_at=(), carve=False,
                      batch_rays=128, level_curvature_weight=0.0, level_spacing_weight=weight)
    scene = make_noise_scene(n_values=len(values))
    return Trainer(scene, None, cfg, torch.device("cpu"), init_field=field).train_step()


def test_a_training_step_adds_the_prior_to_its_loss() -> None:
    with_prior, without = _step([0.0, 1.0, 2.0], 0.5), _step([0.0, 1.0, 2.0], 0.0)
    assert with_prior["level_spacing"] > 0
    assert "level_spacing" not in without
    assert with_prior["mse"] == pytest.approx(without["mse"], rel=1e-6)
    assert with_prior["loss"] - without["loss"] == pytest.approx(with_prior["level_spacing"], rel=1e-4)
    assert "level_spacing" not in _step([0.0, 1.0], 0.5)  # two levels: no neighbouring bands
