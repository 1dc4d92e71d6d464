"""Parameter axes: the monotone cubic between knots (against SciPy's PCHIP), its gradients, and
vectors of ones leaving features unchanged; the level axis's natural spline (against SciPy's)."""

import numpy as np
import pytest
import torch
from scipy.interpolate import CubicSpline, PchipInterpolator

from visnerf.representation.param_axes import (
    ParamAxes,
    distinct_rows,
    interpolate_knots,
    interpolate_natural_spline,
    knot_rows,
    natural_spline_curvatures,
    pchip_slopes,
)


def test_knot_rows_exactly_and_ends_held():
    table = torch.tensor([[1.0], [3.0], [7.0]])
    knots = torch.tensor([-1.0, 0.0, 1.0])
    x = torch.tensor([-3.0, -1.0, 0.0, 1.0, 2.0])
    assert torch.equal(interpolate_knots(table, knots, x)[:, 0], torch.tensor([1.0, 1.0, 3.0, 7.0, 7.0]))


def test_knot_rows_finds_knots_only_when_every_value_is_one():
    knots = torch.tensor([-1.0, -0.25, 0.5, 1.0])
    assert torch.equal(knot_rows(knots, torch.tensor([1.0, -1.0, 0.5, 0.5, -0.25])), torch.tensor([3, 0, 2, 2, 1]))
    assert knot_rows(knots, torch.tensor([1.0, 0.4999999])) is None
    assert knot_rows(knots, torch.tensor([-1.0, 1.5])) is None
    assert knot_rows(knots, torch.tensor([-1.0, float("nan")])) is None


@pytest.mark.parametrize("interpolant", ["monotone", "natural"])
def test_values_at_knots_gather_the_rows_as_the_interpolant_gives_them(monkeypatch, interpolant):
    """At the knots (where training reads the tables) the gathered rows equal the full
    interpolant's, in value and in the table's gradient, bit for bit."""
    import visnerf.representation.param_axes as param_axes

    gen = torch.Generator().manual_seed(5)
    knots = torch.tensor([-1.0, -0.4, 0.1, 0.55, 1.0], dtype=torch.float64)
    table = torch.randn(5, 3 if interpolant == "monotone" else 1, generator=gen, dtype=torch.float64)
    x = knots[torch.tensor([0, 4, 2, 2, 1, 3, 0])]
    weights = torch.randn(7, table.shape[1], generator=gen, dtype=torch.float64)

    def run() -> tuple[torch.Tensor, torch.Tensor]:
        t = table.clone().requires_grad_(True)
        out = interpolate_knots(t, knots, x) if interpolant == "monotone" else interpolate_natural_spline(t[:, 0], knots, x)[:, None]
        (out * weights).sum().backward()
        return out.detach(), t.grad

    gathered, grad = run()
    monkeypatch.setattr(param_axes, "knot_rows", lambda knots, x: None)  # the interpolant in full
    full, full_grad = run()
    assert torch.equal(gathered, full) and torch.equal(grad, full_grad)
    assert torch.equal(gathered, table[torch.tensor([0, 4, 2, 2, 1, 3, 0])])


def test_rows_on_a_line_stay_on_it():
    knots = torch.tensor([-1.0, -0.2, 0.1, 1.0], dtype=torch.float64)
    table = torch.stack([2.0 * knots - 1.0, -0.5 * knots + 3.0], dim=1)  # [4, 2], linear in the knot
    x = torch.linspace(-1.0, 1.0, 101, dtype=torch.float64)
    expected = torch.stack([2.0 * x - 1.0, -0.5 * x + 3.0], dim=1)
    assert torch.allclose(interpolate_knots(table, knots, x), expected, atol=1e-12)


def test_two_knots_interpolate_linearly():
    table = torch.tensor([[1.0, -2.0], [3.0, 4.0]], dtype=torch.float64)
    knots = torch.tensor([-0.5, 0.5], dtype=torch.float64)
    x = torch.tensor([-0.5, -0.25, 0.0, 0.3, 0.5], dtype=torch.float64)
    s = (x + 0.5)[:, None]
    assert torch.allclose(interpolate_knots(table, knots, x), table[0] * (1 - s) + table[1] * s, atol=1e-14)


@pytest.mark.parametrize("m", [3, 4, 5, 9])
def test_matches_scipy_pchip(m):
    gen = torch.Generator().manual_seed(m)
    knots = torch.sort(torch.rand(m, generator=gen, dtype=torch.float64) * 2 - 1).values
    table = torch.randn(m, 8, generator=gen, dtype=torch.float64)
    table[1, 0] = table[2, 0]  # a flat secant
    table[:, 1] = torch.linspace(0.0, 1.0, m, dtype=torch.float64) ** 3  # monotone and curved
    x = torch.linspace(float(knots[0]), float(knots[-1]), 401, dtype=torch.float64)
    expected = PchipInterpolator(knots.numpy(), table.numpy(), axis=0)(x.numpy())
    np.testing.assert_allclose(interpolate_knots(table, knots, x).numpy(), expected, atol=1e-12)


def test_each_piece_stays_between_its_knot_rows():
    gen = torch.Generator().manual_seed(1)
    knots = torch.tensor([-1.0, -0.6, 0.1, 0.2, 1.0])
    table = torch.randn(5, 16, generator=gen)
    x = torch.linspace(-1.0, 1.0, 1001)
    out = interpolate_knots(table, knots, x)  # [n, 16]
    hi = torch.searchsorted(knots, x).clamp(1, 4)
    low = torch.minimum(table[hi - 1], table[hi])
    high = torch.maximum(table[hi - 1], table[hi])
    assert bool(((out >= low - 1e-6) & (out <= high + 1e-6)).all())


def test_gradients_in_the_table_match_finite_differences():
    gen = torch.Generator().manual_seed(2)
    knots = torch.tensor([-1.0, -0.3, 0.4, 1.0], dtype=torch.float64)
    table = torch.randn(4, 3, generator=gen, dtype=torch.float64)
    table[:, 2] = torch.tensor([0.0, 1.0, 0.2, -0.5], dtype=torch.float64)  # turns at a knot
    # (a flat secant is a kink of the slopes, where finite differences do not apply; see below)
    x = torch.tensor([-0.8, -0.31, 0.05, 0.7, 0.99], dtype=torch.float64)
    table.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: interpolate_knots(t, knots, x), (table,))


def test_gradients_finite_where_every_secant_is_flat():
    table = torch.ones(5, 4, requires_grad=True)  # a fresh field's tables
    out = interpolate_knots(table, torch.linspace(-1.0, 1.0, 5), torch.rand(32) * 2 - 1)
    out.sum().backward()
    assert torch.isfinite(table.grad).all()
    assert torch.equal(out, torch.ones(32, 4))


def test_slopes_are_zero_where_a_column_turns():
    knots = torch.tensor([0.0, 1.0, 2.0])
    table = torch.tensor([[0.0], [1.0], [0.0]])
    assert float(pchip_slopes(table, knots)[1, 0]) == 0.0


def test_param_axes_of_ones_leave_features_unchanged():
    axes = ParamAxes((3, 5), 4)
    assert torch.equal(axes.sample(torch.rand(10, 2) * 2 - 1), torch.ones(10, 4))


def test_level_axis_starts_flat_and_follows_its_levels_by_the_natural_spline():
    from visnerf.representation.param_axes import LevelAxis

    axis = LevelAxis(5)
    x = torch.linspace(-1.5, 1.5, 61)
    assert torch.equal(axis.sample(x), torch.zeros(61))  # every value the same surface at first
    knots = torch.tensor([-1.0, -0.5, 0.0, 0.5, 1.0])
    axis.set_knots(knots)
    with torch.no_grad():  # smooth increasing levels, as a trained sweep's are
        axis.table.copy_(torch.tensor([[-1.9], [-1.2], [-0.3], [0.6], [1.2]]))
    levels = axis.sample(x)
    assert torch.allclose(axis.sample(knots), axis.table[:, 0])
    assert bool((levels[1:] >= levels[:-1]).all())  # increasing levels stay increasing between knots
    assert levels[0] == -1.9 and levels[-1] == 1.2  # held at the ends
    expected = CubicSpline(knots.double().numpy(), axis.table[:, 0].double().detach().numpy(), bc_type="natural")(
        x.clamp(-1.0, 1.0).double().numpy())
    assert np.allclose(levels.detach().numpy(), expected, atol=1e-5)
    levels.sum().backward()
    assert axis.table.grad is not None and torch.isfinite(axis.table.grad).all()


@pytest.mark.parametrize("m", [3, 4, 5, 9])
def test_natural_spline_matches_scipy_on_smooth_data(m):
    gen = torch.Generator().manual_seed(m)
    knots = torch.sort(torch.rand(m, generator=gen, dtype=torch.float64) * 2 - 1).values
    knots[0], knots[-1] = -1.0, 1.0
    table = torch.exp(knots)  # smooth and increasing: no piece leaves its knot values
    x = torch.linspace(-1.0, 1.0, 401, dtype=torch.float64)
    expected = CubicSpline(knots.numpy(), table.numpy(), bc_type="natural")(x.numpy())
    np.testing.assert_allclose(interpolate_natural_spline(table, knots, x).numpy(), expected, atol=1e-12)
    curvatures = CubicSpline(knots.numpy(), table.numpy(), bc_type="natural")(knots.numpy(), 2)
    np.testing.assert_allclose(natural_spline_curvatures(table, knots).numpy(), curvatures, atol=1e-10)


def test_natural_spline_of_few_knots_and_of_a_line():
    x = torch.tensor([-2.0, -1.0, -0.3, 0.4, 1.0, 3.0], dtype=torch.float64)
    assert torch.equal(interpolate_natural_spline(torch.tensor([2.5], dtype=torch.float64),
                                                  torch.zeros(1, dtype=torch.float64), x), torch.full((6,), 2.5,
                                                                                                     dtype=torch.float64))
    two = interpolate_natural_spline(torch.tensor([1.0, 3.0], dtype=torch.float64),
                                     torch.tensor([-1.0, 1.0], dtype=torch.float64), x)
    assert torch.allclose(two, 2.0 + x.clamp(-1.0, 1.0), atol=1e-14)
    knots = torch.tensor([-1.0, -0.2, 0.1, 0.7, 1.0], dtype=torch.float64)
    assert torch.allclose(interpolate_natural_spline(3.0 * knots - 1.0, knots, x), 3.0 * x.clamp(-1.0, 1.0) - 1.0,
                          atol=1e-12)  # data on a line: zero curvature, the line itself


def test_natural_spline_pieces_stay_between_their_knot_values():
    knots = torch.tensor([-1.0, -0.5, 0.0, 0.5, 1.0])
    table = torch.tensor([0.0, 0.0, 0.0, 1.0, 1.0])  # a step: the bare spline overshoots on both sides
    x = torch.linspace(-1.0, 1.0, 1001)
    bare = CubicSpline(knots.numpy(), table.numpy(), bc_type="natural")(x.numpy())
    assert bare.min() < -0.01 and bare.max() > 1.01
    out = interpolate_natural_spline(table, knots, x)
    hi = torch.searchsorted(knots, x).clamp(1, 4)
    assert bool(((out >= torch.minimum(table[hi - 1], table[hi])) & (out <= torch.maximum(table[hi - 1], table[hi]))).all())


def test_natural_spline_gradients_match_finite_differences():
    knots = torch.tensor([-1.0, -0.4, 0.2, 0.6, 1.0], dtype=torch.float64)
    table = torch.tensor([-1.5, -0.9, -0.1, 0.5, 1.4], dtype=torch.float64, requires_grad=True)
    x = torch.tensor([-0.9, -0.45, 0.0, 0.33, 0.8], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda t: interpolate_natural_spline(t, knots, x), (table,))


def test_level_axis_refuses_knots_that_do_not_fit():
    from visnerf.representation.param_axes import LevelAxis

    axis = LevelAxis(3)
    with pytest.raises(ValueError, match="3 values, got 2"):
        axis.set_knots(torch.tensor([-1.0, 1.0]))
    with pytest.raises(ValueError, match="strictly increasing"):
        axis.set_knots(torch.tensor([-1.0, 0.5, 0.5]))


@pytest.mark.parametrize("k", [1, 2, 3])
def test_distinct_rows_is_unique_over_rows(k) -> None:
    """Against ``torch.unique(dim=0)``: the same sorted rows and the same inverse, with values
    repeated across columns and rows, and signed zeros and extremes among them."""
    g = torch.Generator().manual_seed(k)
    pool = torch.tensor([-1.0, -0.25, 0.0, 1e-7, 0.5, 1.0])
    params = pool[torch.randint(0, pool.numel(), (2048, k), generator=g)]
    settings, which = distinct_rows(params)
    expected, inverse = torch.unique(params, dim=0, return_inverse=True)
    assert torch.equal(settings, expected)
    assert torch.equal(which, inverse)
    assert torch.equal(settings[which], params)
