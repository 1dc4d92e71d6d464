"""The paper's capture protocol: training views on an icosphere, a test path with moving parameters.

- Training: every parameter setting (the Cartesian product of each axis' evenly spaced values) is
  seen from the same views: the 42 vertices of a level-1 icosphere (other counts: the icosphere
  of that level if there is one, 12 / 42 / 162 / 642, else a Fibonacci sphere).
- Test: ``n_views`` cameras on a path from (azimuth -180, elevation -90) through (0, 0) to
  (180, 90), linear in both angles, while the parameters move through their ranges, always
  strictly between training values (see ``path_params``).
Angles follow ``visnerf.data.cameras.orbit_c2w`` (degrees, +y up, azimuth 0 on +z).
"""

import itertools
import math
from dataclasses import dataclass

import numpy as np
from jaxtyping import Float


@dataclass(frozen=True)
class ParamAxis:
    """One varying parameter of a scene and its training values."""

    name: str
    """Name written to ``param_names``."""
    low: float
    """First training value."""
    high: float
    """Last training value."""
    count: int
    """Number of evenly spaced training values (>= 2)."""
    description: str = ""
    """What the parameter does, for ``visnerf scenes``."""

    def __post_init__(self) -> None:
        if self.count < 2 or not self.high > self.low:
            raise ValueError(f"axis {self.name!r} needs count >= 2 and high > low")

    def values(self) -> tuple[float, ...]:
        """The training values, evenly spaced from ``low`` to ``high``."""
        return tuple(float(v) for v in np.linspace(self.low, self.high, self.count))


def icosphere_vertices(level: int) -> Float[np.ndarray, "n 3"]:
    """Unit vertices of an icosahedron subdivided ``level`` times (12, 42, 162, 642, ... vertices)."""
    phi = (1.0 + math.sqrt(5.0)) / 2.0
    vertices = [
        (-1, phi, 0), (1, phi, 0), (-1, -phi, 0), (1, -phi, 0),
        (0, -1, phi), (0, 1, phi), (0, -1, -phi), (0, 1, -phi),
        (phi, 0, -1), (phi, 0, 1), (-phi, 0, -1), (-phi, 0, 1),
    ]  # fmt: skip
    faces = [
        (0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11),
        (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6), (7, 1, 8),
        (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9),
        (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1),
    ]  # fmt: skip
    points = [np.asarray(v, dtype=np.float64) / np.linalg.norm(v) for v in vertices]
    for _ in range(level):
        midpoints: dict[tuple[int, int], int] = {}
        refined = []
        for a, b, c in faces:
            ab, bc, ca = (_midpoint(points, midpoints, i, j) for i, j in ((a, b), (b, c), (c, a)))
            refined += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = refined
    return np.stack(points)


def _midpoint(points: list, cache: dict, i: int, j: int) -> int:
    key = (min(i, j), max(i, j))
    if key not in cache:
        mid = points[i] + points[j]
        points.append(mid / np.linalg.norm(mid))
        cache[key] = len(points) - 1
    return cache[key]


def fibonacci_sphere(n: int) -> Float[np.ndarray, "n 3"]:
    """``n`` nearly uniform unit vectors (golden-angle spiral from +y to -y)."""
    i = np.arange(n, dtype=np.float64) + 0.5
    y = 1.0 - 2.0 * i / n
    radius = np.sqrt(1.0 - y * y)
    angle = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([radius * np.sin(angle), y, radius * np.cos(angle)], axis=-1)


def training_directions(n_views: int) -> Float[np.ndarray, "n 3"]:
    """Unit directions from the target to the training cameras."""
    if n_views < 1:
        raise ValueError(f"need at least one training view, got {n_views}")
    for level in range(4):
        if 10 * 4**level + 2 == n_views:
            return icosphere_vertices(level)
    return fibonacci_sphere(n_views)


def direction_to_angles(direction: Float[np.ndarray, " 3"]) -> tuple[float, float]:
    """(azimuth, elevation) in degrees of a unit direction, as ``orbit_c2w`` takes them."""
    x, y, z = (float(c) for c in direction)
    return math.degrees(math.atan2(x, z)), math.degrees(math.asin(max(-1.0, min(1.0, y))))


def parameter_settings(axes: tuple[ParamAxis, ...]) -> list[tuple[float, ...]]:
    """Every combination of the axes' training values, the last axis varying fastest."""
    return [tuple(combo) for combo in itertools.product(*(axis.values() for axis in axes))]


def path_angles(n_views: int) -> list[tuple[float, float]]:
    """(azimuth, elevation) in degrees: from (-180, -90) through (0, 0) to (180, 90), linearly."""
    if n_views < 2:
        raise ValueError(f"the test path needs at least two views, got {n_views}")
    s = np.linspace(0.0, 1.0, n_views)
    return [(float(-180.0 + 360.0 * f), float(-90.0 + 180.0 * f)) for f in s]


def squeezed_sweep(axis: ParamAxis, fraction: float) -> float:
    """The axis' value at ``fraction`` (0 to 1) of a sweep that stays between training values.

    The fractional training index ``x = fraction * (count - 1)`` is squeezed into the middle half of
    its interval, ``k + 0.25 + 0.5 * (x - k)`` with ``k = floor(x)``: the value rises monotonically
    from a quarter of a spacing above ``low`` to a quarter below ``high`` and never comes closer
    than a quarter of a spacing to a training value.
    """
    values = axis.values()
    x = min(max(fraction, 0.0), 1.0) * (axis.count - 1)
    k = min(int(math.floor(x)), axis.count - 2)
    return float(values[k] + (0.25 + 0.5 * (x - k)) * (values[k + 1] - values[k]))


def path_params(axes: tuple[ParamAxis, ...], n_views: int) -> list[tuple[float, ...]]:
    """Parameter values at each test view, all strictly between training values.

    One axis: it sweeps its range along the whole path. Several axes (the paper's Nyx protocol):
    the first half of the path varies one axis at a time (in equal segments each axis in turn swings
    from the middle of its sweep up, down and back, ``0.5 + 0.5 sin(2 pi f)``, the others staying in
    the middle), the second half sweeps all of them together.
    """
    if not axes:
        return [() for _ in range(n_views)]
    if len(axes) == 1:
        return [(squeezed_sweep(axes[0], float(f)),) for f in np.linspace(0.0, 1.0, n_views)]
    n_single = n_views // 2
    segment = max(n_single // len(axes), 1)
    out = []
    for i in range(n_views):
        if i < n_single:
            moving = min(i // segment, len(axes) - 1)
            first = moving * segment
            last = n_single - 1 if moving == len(axes) - 1 else first + segment - 1
            swing = 0.5 + 0.5 * math.sin(2.0 * math.pi * (i - first) / max(last - first, 1))
            out.append(tuple(squeezed_sweep(a, swing if j == moving else 0.5) for j, a in enumerate(axes)))
        else:
            f = (i - n_single) / max(n_views - n_single - 1, 1)
            out.append(tuple(squeezed_sweep(a, f) for a in axes))
    return out
