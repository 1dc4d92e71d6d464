"""Capture protocol, transfer functions and fields: closed forms and properties."""

import math

import numpy as np
import pytest
import torch

from visnerf.data.cameras import orbit_c2w
from visnerf.scenes.catalog import get_scene, scene_catalog
from visnerf.scenes.fields import CosmicWebField, TangleField, radial_window
from visnerf.scenes.protocol import (
    ParamAxis,
    direction_to_angles,
    icosphere_vertices,
    parameter_settings,
    path_angles,
    path_params,
    training_directions,
)
from visnerf.scenes.transfer_function import TransferFunction, corrected_opacity


def test_level_one_icosphere_has_42_evenly_spread_unit_vertices() -> None:
    """12 icosahedron vertices + 30 edge midpoints; nearest-neighbour angles 31.7 - 36.0 degrees."""
    vertices = icosphere_vertices(1)
    assert vertices.shape == (42, 3)
    assert np.allclose(np.linalg.norm(vertices, axis=1), 1.0)
    cosines = vertices @ vertices.T - 2.0 * np.eye(42)
    nearest = np.degrees(np.arccos(np.clip(cosines.max(axis=1), -1.0, 1.0)))
    assert nearest.min() > 31.0 and nearest.max() < 36.5
    assert np.allclose(vertices.mean(axis=0), 0.0, atol=1e-12)  # symmetric: no preferred side
    assert training_directions(42).shape == (42, 3) and training_directions(12).shape == (12, 3)
    assert training_directions(30).shape == (30, 3)  # not an icosphere count: Fibonacci sphere


def test_cameras_sit_on_the_view_directions_and_look_at_the_centre() -> None:
    for direction in icosphere_vertices(1):
        azimuth, elevation = direction_to_angles(direction)
        c2w = orbit_c2w(azimuth, elevation, 2.1)
        assert np.allclose(c2w[:3, 3], 2.1 * direction, atol=1e-9)
        assert np.allclose(c2w[:3, 2], direction, atol=1e-9)  # camera looks down -z, at the origin


def test_parameter_settings_are_the_grid_of_evenly_spaced_values() -> None:
    a, b = ParamAxis("a", 0.0, 1.0, 3), ParamAxis("b", -1.0, 1.0, 2)
    assert a.values() == (0.0, 0.5, 1.0)
    assert parameter_settings((a, b)) == [
        (0.0, -1.0),
        (0.0, 1.0),
        (0.5, -1.0),
        (0.5, 1.0),
        (1.0, -1.0),
        (1.0, 1.0),
    ]
    assert parameter_settings(()) == [()]
    with pytest.raises(ValueError):
        ParamAxis("c", 1.0, 1.0, 3)


def test_test_path_runs_from_minus_180_minus_90_through_0_0_to_180_90() -> None:
    angles = path_angles(181)
    assert angles[0] == (-180.0, -90.0) and angles[90] == (0.0, 0.0) and angles[180] == (180.0, 90.0)
    assert all(
        b[0] - a[0] == pytest.approx(2.0) and b[1] - a[1] == pytest.approx(1.0)
        for a, b in zip(angles, angles[1:], strict=False)
    )


@pytest.mark.parametrize("name", sorted(scene_catalog()))
def test_test_path_params_stay_strictly_between_training_values(name: str) -> None:
    axes = get_scene(name).axes
    rows = path_params(axes, 181)
    assert len(rows) == 181 and all(len(row) == len(axes) for row in rows)
    for j, axis in enumerate(axes):
        values = np.array(axis.values())
        spacing = values[1] - values[0]
        column = np.array([row[j] for row in rows])
        assert column.min() >= axis.low and column.max() <= axis.high
        gap = np.abs(column[:, None] - values[None, :]).min(axis=1)
        assert gap.min() >= 0.25 * spacing - 1e-12
        assert column.max() - column.min() >= 0.7 * (axis.high - axis.low)  # it sweeps the range


def test_several_parameters_move_one_at_a_time_then_together() -> None:
    axes = get_scene("cosmo_sim").axes
    rows = np.array(path_params(axes, 181))
    moving = (np.abs(np.diff(rows[:90], axis=0)) > 0).sum(axis=1)
    assert moving.max() == 1  # first half: one parameter at a time
    for j in range(3):  # ... each swinging over most of its range
        assert np.ptp(rows[30 * j : 30 * j + 30, j]) >= 0.6 * (axes[j].high - axes[j].low)
    assert np.all(np.abs(np.diff(rows[90:], axis=0)).min(axis=0) >= 0)
    assert all(len(set(rows[90:, j])) > 40 for j in range(3))  # second half: all three together


def test_transfer_function_is_piecewise_linear_with_constant_ends() -> None:
    """Matches numpy.interp on every channel, including beyond the first and last knots."""
    tf = TransferFunction(
        (0.1, 0.3, 0.8), ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (1.0, 0.0, 0.0)), (0.0, 0.5, 1.0)
    )
    v = torch.linspace(-0.5, 1.5, 401, dtype=torch.float64)
    assert np.allclose(tf.opacity(v).numpy(), np.interp(v.numpy(), tf.knots, tf.opacities), atol=1e-12)
    for channel in range(3):
        reference = np.interp(v.numpy(), tf.knots, [c[channel] for c in tf.colours])
        assert np.allclose(tf.colour(v)[:, channel].numpy(), reference, atol=1e-12)
    rgb, sigma = tf.colour_and_extinction(v)
    assert torch.allclose(rgb, tf.colour(v)) and torch.allclose(sigma, tf.extinction(v))
    assert torch.isfinite(sigma).all()  # opacity 1 is clamped to max_opacity
    with pytest.raises(ValueError):
        TransferFunction((0.5, 0.5), ((0.0, 0.0, 0.0),) * 2, (0.0, 1.0))


def test_opacity_correction_composes_over_steps() -> None:
    """Two slabs of half the reference thickness compose to one: 1 - (1 - a_half)^2 = a.

    With a = 0.75: a_half = 1 - 0.25^0.5 = 0.5, and 1 - 0.5^2 = 0.75.
    """
    a = torch.tensor([0.0, 0.3, 0.75, 0.99], dtype=torch.float64)
    half = corrected_opacity(a, 0.005, 0.01)
    assert half[2].item() == pytest.approx(0.5, abs=1e-12)
    assert torch.allclose(1.0 - (1.0 - half) ** 2, a, atol=1e-12)
    assert torch.allclose(corrected_opacity(a, 0.01, 0.01), a, atol=1e-12)


def test_tangle_values_at_its_critical_points() -> None:
    """v = -sum(q^4 - 5 q^2) / 18.75 with q = 8 p: 1 at blob centres (q = +-sqrt 2.5), 0 at the
    origin, 2/3 at edge saddles (two coordinates +-sqrt 2.5), 1/3 at face saddles (one)."""
    c = math.sqrt(2.5) / 8.0
    points = torch.tensor(
        [[c, c, c], [-c, c, -c], [0.0, 0.0, 0.0], [c, -c, 0.0], [0.0, 0.0, c]], dtype=torch.float64
    )
    assert torch.allclose(
        TangleField()(points), torch.tensor([1.0, 1.0, 0.0, 2 / 3, 1 / 3], dtype=torch.float64)
    )


def test_cosmic_field_has_unit_variance_modes() -> None:
    """sum(A^2) / 2 = 1: the random field delta has unit variance for every parameter setting."""
    for params in ((0.12, 0.0215, 0.55), (0.16, 0.0235, 0.85)):
        _, _, amplitude = CosmicWebField(*params).modes(torch.float64, torch.device("cpu"))
        assert amplitude.square().sum().item() / 2.0 == pytest.approx(1.0)


@pytest.mark.parametrize("name", sorted(scene_catalog()))
def test_scene_fields_are_finite_and_vanish_outside_the_content_ball(name: str) -> None:
    spec = get_scene(name)
    generator = torch.Generator().manual_seed(0)
    points = torch.rand(4000, 3, generator=generator) * 1.4 - 0.7  # [n, 3] box [-0.7, 0.7]^3
    outside = torch.linalg.norm(points, dim=1) > 0.5
    for setting in parameter_settings(spec.axes)[:: max(1, len(parameter_settings(spec.axes)) // 4)]:
        values = spec.volume_at(setting).field(points)
        assert values.shape == (4000,) and torch.isfinite(values).all()
        assert torch.all(values[outside] == 0.0)
    assert torch.all(radial_window(points)[outside] == 0.0)
