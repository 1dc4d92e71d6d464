"""Interpolation primitives against closed forms and an independent implementation (scipy)."""

import math

import numpy as np
import pytest
import torch

from visnerf.animation.splines import catmull_rom, cross3, lerp, pchip, slerp, turn_between
from visnerf.representation.param_axes import pchip_slopes


def unit(az_deg: float, el_deg: float) -> np.ndarray:
    az, el = math.radians(az_deg), math.radians(el_deg)
    return np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])


def angle(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(a @ b, -1.0, 1.0))))


@pytest.mark.parametrize("u", [-0.5, 0.0, 0.25, 0.5, 1.0, 1.75])
def test_slerp_follows_the_great_circle_at_a_constant_rate(u: float) -> None:
    # on the equator: a at azimuth 10, b at azimuth 70 -> the point at azimuth 10 + 60 u
    out = slerp(unit(10, 0), unit(70, 0), u)
    np.testing.assert_allclose(out, unit(10 + 60 * u, 0), atol=1e-12)
    assert abs(np.linalg.norm(out) - 1.0) < 1e-12


def test_slerp_takes_the_short_way_across_azimuth_180() -> None:
    mid = slerp(unit(179, 0), unit(-179, 0), 0.5)
    np.testing.assert_allclose(mid, unit(180, 0), atol=1e-12)


def test_slerp_of_antipodes_stays_a_unit_vector_a_right_angle_away() -> None:
    a = unit(0, 0)
    mid = slerp(a, -a, 0.5)
    assert abs(np.linalg.norm(mid) - 1.0) < 1e-12 and abs(angle(a, mid) - 90.0) < 1e-9


def test_euclidean_catmull_rom_equals_the_uniform_closed_form() -> None:
    rng = np.random.default_rng(0)
    p = rng.normal(size=(4, 3))
    for s in (0.0, 0.3, 0.5, 0.9, 1.0):
        expected = 0.5 * (2 * p[1] + (p[2] - p[0]) * s + (2 * p[0] - 5 * p[1] + 4 * p[2] - p[3]) * s**2
                          + (3 * p[1] - p[0] - 3 * p[2] + p[3]) * s**3)
        got = catmull_rom((p[0], p[1], p[2], p[3]), (0.0, 1.0, 2.0, 3.0), 1.0 + s, lerp)
        np.testing.assert_allclose(got, expected, atol=1e-12)


def test_spherical_catmull_rom_is_exact_on_a_great_circle_with_uneven_knots() -> None:
    # points on a tilted great circle at angles proportional to their (uneven) times
    axis = np.array([0.3, 1.0, -0.2]) / np.linalg.norm([0.3, 1.0, -0.2])
    start = np.cross(axis, [1.0, 0.0, 0.0])
    start /= np.linalg.norm(start)
    other = np.cross(axis, start)

    def on_circle(deg: float) -> np.ndarray:
        return start * math.cos(math.radians(deg)) + other * math.sin(math.radians(deg))

    times = (0.0, 0.4, 1.5, 1.7)
    rate = 50.0  # degrees a second
    points = tuple(on_circle(rate * t) for t in times)
    for t in np.linspace(0.4, 1.5, 7):
        got = catmull_rom(points, times, float(t), slerp)  # type: ignore[arg-type]
        np.testing.assert_allclose(got, on_circle(rate * t), atol=1e-12)


def test_spherical_catmull_rom_passes_through_its_keyframes() -> None:
    points = (unit(0, 10), unit(80, 40), unit(150, -20), unit(170, 60))
    times = (0.0, 1.0, 3.0, 3.5)
    np.testing.assert_allclose(catmull_rom(points, times, 1.0, slerp), points[1], atol=1e-12)
    np.testing.assert_allclose(catmull_rom(points, times, 3.0, slerp), points[2], atol=1e-12)


def test_pchip_equals_scipy() -> None:
    scipy_interpolate = pytest.importorskip("scipy.interpolate")
    x = np.array([0.0, 0.5, 1.7, 2.0, 3.5, 4.0])
    y = np.array([0.0, 1.0, 1.0, 0.2, 0.9, 0.1])
    reference = scipy_interpolate.PchipInterpolator(x, y)
    slopes = pchip_slopes(torch.as_tensor(y)[:, None], torch.as_tensor(x))[:, 0].numpy()
    np.testing.assert_allclose(slopes, reference.derivative()(x), atol=1e-12)
    for t in np.linspace(0.0, 4.0, 41):
        assert pchip(x, y, float(t)) == pytest.approx(float(reference(t)), abs=1e-12)


def test_pchip_reproduces_a_straight_line_and_never_overshoots() -> None:
    x = np.array([0.0, 1.0, 1.5, 4.0])
    np.testing.assert_allclose([pchip(x, 2.0 * x + 1.0, t) for t in (0.2, 1.2, 3.0)], [1.4, 3.4, 7.0], atol=1e-12)
    y = np.array([0.0, 1.0, 1.0, 0.0])  # a plateau: a classical spline bulges above 1 here
    values = [pchip(x, y, float(t)) for t in np.linspace(0.0, 4.0, 401)]
    assert min(values) >= 0.0 and max(values) <= 1.0


def test_turn_between_is_the_smallest_rotation() -> None:
    a, b = unit(10, 20), unit(60, -10)
    np.testing.assert_allclose(turn_between(a, b, a), b, atol=1e-12)
    normal = np.cross(a, b) / np.linalg.norm(np.cross(a, b))
    np.testing.assert_allclose(turn_between(a, b, normal), normal, atol=1e-12)  # the axis stays
    v = np.array([0.3, -0.7, 0.2])
    assert np.linalg.norm(turn_between(a, b, v)) == pytest.approx(np.linalg.norm(v), abs=1e-12)
    np.testing.assert_allclose(turn_between(a, -a, a), -a, atol=1e-12)


def test_cross3_equals_numpy() -> None:
    rng = np.random.default_rng(1)
    for a, b in rng.normal(size=(5, 2, 3)):
        np.testing.assert_allclose(cross3(a, b), np.cross(a, b), atol=1e-14)
