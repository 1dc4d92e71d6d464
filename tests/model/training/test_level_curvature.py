"""The curvature prior of a level axis's field ``g`` against closed forms (zero for a linear field,
``(8 c h^2)^2 / span^2`` for ``c |x|^2`` in grid coordinates, unchanged when ``g`` and the levels
are scaled together, nothing for a field without a level axis), and its place in a training step."""

import pytest
import torch

from visnerf.config import TrainConfig
from visnerf.testing import make_noise_scene, make_tiny_field
from visnerf.training.regularizers import LEVEL_SPAN_EPS, level_curvature
from visnerf.training.trainer import Trainer

ISOVALUES = [("isovalue", [0.2, 0.4, 0.6])]


def _level_field(levels: list[float]):
    field, _ = make_tiny_field(ISOVALUES, seed=2, resolution=9, level_set_axis=0)
    with torch.no_grad():
        field.levels.table.copy_(torch.tensor(levels)[:, None])
    return field


def _with_g(field, g) -> None:
    """Replace the density decoder's output by ``g(coords)`` (grid coordinates)."""
    field.raw_density = lambda coords, spatial, q: g(coords) + 0.0 * spatial.sum(-1)  # keeps the graph


def _params(n: int) -> torch.Tensor:
    return torch.zeros(n, 1)


def test_a_linear_field_has_no_curvature() -> None:
    field = _level_field([0.0, 1.0, 3.0])
    _with_g(field, lambda x: 2.0 * x[:, 0] - 0.7 * x[:, 1] + 0.3 * x[:, 2] + 5.0)
    value = level_curvature(field, _params(512), torch.Generator().manual_seed(0))
    assert float(value.detach()) < 1e-10


def test_a_quadratic_field_matches_its_closed_form() -> None:
    c, span = 1.7, 3.0
    field = _level_field([0.0, 1.0, span])
    _with_g(field, lambda x: c * x.pow(2).sum(-1))
    # the box is [-0.5, 0.5]^3: grid coordinates are twice the world's, g = 4c |p|^2, whose second
    # difference along any unit direction at step h is 8 c h^2 everywhere
    h = 2.0 * field.voxel_size()
    value = level_curvature(field, _params(256), torch.Generator().manual_seed(1), step_voxels=2.0)
    expected = (8.0 * c * h * h) ** 2 / (span * span + LEVEL_SPAN_EPS)
    assert float(value.detach()) == pytest.approx(expected, rel=1e-4)


def test_scaling_the_field_and_its_levels_together_changes_nothing() -> None:
    def bumpy(x: torch.Tensor) -> torch.Tensor:
        return torch.sin(3.0 * x[:, 0]) * torch.cos(2.0 * x[:, 1]) + x[:, 2] ** 3

    values = []
    for scale in (1.0, 40.0):
        field = _level_field([scale * v for v in (-1.0, 0.5, 2.0)])
        _with_g(field, lambda x, s=scale: s * bumpy(x))
        values.append(float(level_curvature(field, _params(300), torch.Generator().manual_seed(4)).detach()))
    assert values[0] > 1e-6
    assert values[1] == pytest.approx(values[0], rel=1e-3)


def test_its_gradient_reaches_the_density_branch_and_the_levels_only() -> None:
    field = _level_field([0.0, 1.0, 3.0])
    level_curvature(field, _params(300), torch.Generator().manual_seed(0)).backward()
    assert field.density_grid.plane_table.grad.abs().sum() > 0
    assert field.density_decoder.hidden.weight.grad.abs().sum() > 0
    assert field.levels.table.grad.abs().sum() > 0  # through the span
    assert field.appearance_grid.plane_table.grad is None
    assert field.color_decoder.hidden.weight.grad is None


def test_a_field_without_a_level_axis_gets_nothing() -> None:
    field, _ = make_tiny_field(ISOVALUES, seed=2, resolution=9)
    value = level_curvature(field, _params(64), torch.Generator().manual_seed(0))
    assert float(value) == 0.0


def _step(level_set_axis: int, weight: float) -> dict[str, float]:
    field, _ = make_tiny_field([("t", [0.0, 1.0])], seed=1, resolution=8, level_set_axis=level_set_axis)
    cfg = TrainConfig(iterations=10, resolution_init=8, resolution_final=8, occupancy_at=(), carve=False,
                      batch_rays=128, level_curvature_weight=weight, level_curvature_points=64)
    return Trainer(make_noise_scene(), None, cfg, torch.device("cpu"), init_field=field).train_step()


def test_a_training_step_of_a_level_axis_adds_the_prior_to_its_loss() -> None:
    with_prior, without = _step(0, 2.0), _step(0, 0.0)
    assert with_prior["level_curvature"] > 0
    assert "level_curvature" not in without
    assert with_prior["mse"] == pytest.approx(without["mse"], rel=1e-6)  # the same rays: the prior draws after them
    assert with_prior["loss"] - without["loss"] == pytest.approx(with_prior["level_curvature"], rel=1e-4)


def test_a_training_step_without_a_level_axis_has_no_prior() -> None:
    assert "level_curvature" not in _step(-1, 2.0)
