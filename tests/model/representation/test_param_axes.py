"""Parameter axes: interpolation between knots, and vectors of ones leave features unchanged."""

import torch

from visnerf.representation.param_axes import ParamAxes, interpolate_knots


def test_param_interpolation_ends_and_between():
    table = torch.tensor([[1.0], [3.0], [7.0]])
    knots = torch.tensor([-1.0, 0.0, 1.0])
    x = torch.tensor([-1.0, -0.5, 0.0, 0.25, 1.0, 2.0])
    out = interpolate_knots(table, knots, x)[:, 0]
    assert torch.allclose(out, torch.tensor([1.0, 2.0, 3.0, 4.0, 7.0, 7.0]))


def test_param_axes_of_ones_leave_features_unchanged():
    axes = ParamAxes((3, 5), 4)
    assert torch.equal(axes.sample(torch.rand(10, 2) * 2 - 1), torch.ones(10, 4))
