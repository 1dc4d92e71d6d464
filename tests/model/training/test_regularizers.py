"""The priors' gradients added in place equal autograd's gradients of ``regularization``."""

import pytest
import torch

from visnerf.representation.vm import VMGrid
from visnerf.testing import make_tiny_field
from visnerf.training.regularizers import (
    RegularizerWeights,
    add_grid_l1_,
    add_grid_total_variation_,
    add_param_priors_,
    backward_regularization,
    regularization,
)

WEIGHTS = RegularizerWeights(l1_density=3e-4, param_l1=2e-4, tv_density=0.05, tv_appearance=0.01, tv_params=0.02)


def _field():
    field, _ = make_tiny_field([("a", [0.0, 0.5, 1.0]), ("b", [1.0, 2.0])], seed=3, resolution=7)
    field.density_grid.resample((5, 7, 6))  # unequal axes: every difference direction is its own size
    field.appearance_grid.resample((5, 7, 6))
    gen = torch.Generator().manual_seed(5)
    with torch.no_grad():
        for table in field.density_params.tables:
            table.add_(0.3 * torch.randn(table.shape, generator=gen))
        field.density_grid.plane_table[::7] = 0.0  # sign(0) = 0: autograd's subgradient of |v| too
    return field


def _grads(field) -> list[torch.Tensor]:
    return [p.grad.clone() if p.grad is not None else torch.zeros_like(p) for p in field.parameters()]


def _tv_reference(grid: VMGrid) -> torch.Tensor:
    """Total variation from the planes' ``[c, h, w]`` views, independently of the table layout."""
    total = 0.0
    for plane, line in zip(grid.planes, grid.lines, strict=True):
        total = total + ((plane[:, 1:, :] - plane[:, :-1, :]) ** 2).mean() + ((plane[:, :, 1:] - plane[:, :, :-1]) ** 2).mean()
        total = total + ((line[:, 1:] - line[:, :-1]) ** 2).mean()
    return total / 3


def test_in_place_gradients_equal_autograds() -> None:
    reference = _field()
    expected_values = regularization(reference, WEIGHTS)
    sum(expected_values.values()).backward()
    expected = _grads(reference)

    field = _field()
    values = backward_regularization(field, WEIGHTS)
    assert values.keys() == expected_values.keys()
    for k, v in values.items():
        assert v == pytest.approx(float(expected_values[k].detach()), rel=1e-5)
    for got, want in zip(_grads(field), expected, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-9)


def test_gradients_add_to_what_is_there() -> None:
    field = _field()
    grid = field.appearance_grid
    grid.plane_table.grad = torch.ones_like(grid.plane_table)
    add_grid_total_variation_(grid, 0.5)
    got = grid.plane_table.grad.clone()

    fresh = _field().appearance_grid
    (0.5 * _tv_reference(fresh)).backward()
    torch.testing.assert_close(got, 1.0 + fresh.plane_table.grad, rtol=1e-5, atol=1e-7)


def test_values_match_the_definitions() -> None:
    field = _field()
    grid = field.density_grid
    assert float(add_grid_total_variation_(grid, 2.0)) == pytest.approx(2.0 * float(_tv_reference(grid).detach()), rel=1e-5)
    l1 = sum(p.abs().mean() for p in grid.planes) + sum(line.abs().mean() for line in grid.lines)
    assert float(add_grid_l1_(grid, 3.0)) == pytest.approx(3.0 * float(l1.detach()) / 6, rel=1e-5)


def test_a_grid_one_node_wide_along_an_axis_has_no_difference_there() -> None:
    grid = VMGrid(2, (1 + 1, 3, 4), 0.5)  # two nodes along x: one difference
    value = add_grid_total_variation_(grid, 1.0)
    assert torch.isfinite(value)
    torch.testing.assert_close(value, _tv_reference(grid).detach(), rtol=1e-5, atol=0)


@pytest.mark.parametrize("axes", [[("a", [0.0, 0.5, 1.0]), ("b", [1.0, 2.0]), ("c", [4.0])], []])
def test_the_parameter_terms_in_closed_form_equal_autograds(axes) -> None:
    """A single-value axis has no difference; no axis, no term; the gradient adds to what is there."""
    def field():
        f, _ = make_tiny_field(axes, seed=4, resolution=5)
        gen = torch.Generator().manual_seed(9)
        with torch.no_grad():
            for table in [*f.density_params.tables, *f.appearance_params.tables]:
                table.add_(0.2 * torch.randn(table.shape, generator=gen))
                table.grad = torch.full_like(table, 0.25)
            if axes:
                f.appearance_params.tables[0][0, 0] = 1.0  # sign(0) = 0, as autograd's subgradient of |1 - w|
        return f

    reference = field()
    expected_values = regularization(reference, RegularizerWeights(0.0, 2e-3, 0.0, 0.0, 0.05))
    if expected_values:
        sum(expected_values.values()).backward()
    got = field()
    values = add_param_priors_(got, 2e-3, 0.05)
    assert values.keys() == expected_values.keys() == ({"param_l1", "tv_params"} if axes else set())
    for k, v in values.items():
        assert v == pytest.approx(float(expected_values[k]), rel=1e-6)
    for a, b in zip(got.parameters(), reference.parameters(), strict=True):
        if b.grad is not None:
            torch.testing.assert_close(a.grad, b.grad, rtol=1e-6, atol=1e-9)
