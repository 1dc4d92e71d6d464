"""Nested visual hulls along a parameter axis (``data.nesting``): balls that shrink with the value
nest, balls that move do not, and an axis that changes nothing is not a level axis."""

import torch

from visnerf.data.nesting import axis_nesting

N = 24


def ball(centre: tuple[float, float, float], radius: float) -> torch.Tensor:
    axis = torch.linspace(-1.0, 1.0, N)
    x, y, z = torch.meshgrid(axis, axis, axis, indexing="ij")
    c = torch.tensor(centre)
    return (((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) <= radius**2).reshape(-1)


def test_shrinking_balls_nest_and_say_which_way():
    settings = torch.tensor([[0.1], [0.4], [0.5], [0.9]])
    hulls = [ball((0, 0, 0), r) for r in (0.9, 0.7, 0.6, 0.3)]
    n = axis_nesting(settings, hulls, 0)
    assert n.pairs == 3 and n.outside_shrinking == 0.0 and n.outside_growing > 0.3
    assert n.nested(0.02) and n.shrinking
    grown = axis_nesting(settings, hulls[::-1], 0)  # the same balls at the reversed values grow
    assert grown.nested(0.02) and not grown.shrinking


def test_the_order_is_by_value_not_by_frame_order():
    settings = torch.tensor([[0.9], [0.1], [0.5], [0.4]])
    hulls = [ball((0, 0, 0), r) for r in (0.3, 0.9, 0.6, 0.7)]
    assert axis_nesting(settings, hulls, 0).nested(0.02)


def test_moving_balls_and_unchanged_hulls_do_not_nest():
    settings = torch.tensor([[0.0], [1.0], [2.0]])
    moving = [ball((x, 0, 0), 0.5) for x in (-0.3, 0.0, 0.3)]
    n = axis_nesting(settings, moving, 0)
    assert min(n.outside_shrinking, n.outside_growing) > 0.2 and not n.nested(0.02)
    same = [ball((0, 0, 0), 0.5)] * 3
    still = axis_nesting(settings, same, 0)
    assert still.change == 0.0 and not still.nested(0.02)


def test_pairs_are_taken_with_the_other_axes_held():
    """Two axes: along the first the balls shrink at each value of the second, which moves them;
    pairs across different values of the second axis are never compared."""
    settings, hulls = [], []
    for t, x in ((0.0, -0.4), (1.0, 0.4)):
        for v, r in ((0.2, 0.5), (0.6, 0.3)):
            settings.append([v, t])
            hulls.append(ball((x, 0, 0), r))
    settings_t = torch.tensor(settings)
    first, second = axis_nesting(settings_t, hulls, 0), axis_nesting(settings_t, hulls, 1)
    assert first.pairs == 2 and first.nested(0.02) and first.shrinking
    assert second.pairs == 2 and not second.nested(0.02)
