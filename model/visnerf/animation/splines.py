"""Interpolation primitives for animation paths: slerp and a spherical Catmull-Rom for view
directions, a monotone cubic (PCHIP) for scalars, and the minimal rotation between two directions.

Nothing here knows about cameras or keyframes; all functions take and return numpy in float64.
"""

import math
from collections.abc import Callable

import numpy as np
import torch
from jaxtyping import Float

from visnerf.representation import param_axes

Mix = Callable[[np.ndarray, np.ndarray, float], np.ndarray]
"""``mix(a, b, u)``: the point a fraction ``u`` (any real: outside [0, 1] extrapolates) from a to b."""


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The cross product of two 3-vectors (``np.cross`` costs ten times more on single vectors)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def perpendicular(a: Float[np.ndarray, " 3"]) -> Float[np.ndarray, " 3"]:
    """A unit vector perpendicular to the unit vector ``a`` (a fixed choice, for the antipodal case)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    p = cross3(a, helper)
    return p / np.linalg.norm(p)


def slerp(a: Float[np.ndarray, " 3"], b: Float[np.ndarray, " 3"], u: float) -> Float[np.ndarray, " 3"]:
    """Spherical linear interpolation of unit vectors: ``a`` turned by ``u`` times the angle between
    them, about their common normal (the shortest way; ``u`` outside [0, 1] goes on along the great
    circle). Antipodal vectors turn about a fixed perpendicular of ``a``."""
    c = float(np.clip(a @ b, -1.0, 1.0))
    theta = math.acos(c)
    if theta < 1e-12:
        return a.copy()
    axis = cross3(a, b)  # [3]
    norm = float(np.linalg.norm(axis))
    axis = perpendicular(a) if norm < 1e-12 else axis / norm
    angle = u * theta
    out = a * math.cos(angle) + cross3(axis, a) * math.sin(angle)  # Rodrigues, axis perpendicular to a
    return out / np.linalg.norm(out)


def lerp(a: np.ndarray, b: np.ndarray, u: float) -> np.ndarray:
    """Straight-line interpolation (the Euclidean counterpart of ``slerp``)."""
    return a + u * (b - a)


def catmull_rom(
    points: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    knots: tuple[float, float, float, float],
    t: float,
    mix: Mix = lerp,
) -> np.ndarray:
    """The Catmull-Rom spline through ``points[1]`` (at ``knots[1]``) and ``points[2]`` (at
    ``knots[2]``), at ``t`` in [knots[1], knots[2]], by the Barry-Goldman pyramid.

    The knots are the keyframe times (strictly increasing), so a keyframe held longer is not
    passed faster. With ``mix=lerp`` this is the classical spline (uniform knots:
    ``0.5 (2 P1 + (P2 - P0) s + (2 P0 - 5 P1 + 4 P2 - P3) s^2 + (3 P1 - P0 - 3 P2 + P3) s^3)``);
    with ``mix=slerp`` every step stays on the unit sphere, and points on one great circle at
    angles proportional to their knots give exactly that circle at constant angular speed.
    """
    p0, p1, p2, p3 = points
    t0, t1, t2, t3 = knots
    a1 = mix(p0, p1, (t - t0) / (t1 - t0))
    a2 = mix(p1, p2, (t - t1) / (t2 - t1))
    a3 = mix(p2, p3, (t - t2) / (t3 - t2))
    b1 = mix(a1, a2, (t - t0) / (t2 - t0))
    b2 = mix(a2, a3, (t - t1) / (t3 - t1))
    return mix(b1, b2, (t - t1) / (t2 - t1))


def pchip(x: Float[np.ndarray, " n"], y: Float[np.ndarray, " n"], t: float) -> float:
    """The monotone cubic through (x, y) at ``t`` (held at the end values outside [x0, xn]): the
    parameter tables' interpolant (``representation.param_axes.interpolate_knots``), in float64."""
    table = torch.as_tensor(np.asarray(y, dtype=np.float64))[:, None]  # [n, 1]
    knots = torch.as_tensor(np.asarray(x, dtype=np.float64))
    return float(param_axes.interpolate_knots(table, knots, torch.tensor([float(t)], dtype=torch.float64))[0, 0])


def turn_between(
    a: Float[np.ndarray, " 3"], b: Float[np.ndarray, " 3"], v: Float[np.ndarray, " 3"]
) -> Float[np.ndarray, " 3"]:
    """``v`` turned by the smallest rotation that takes unit ``a`` to unit ``b`` (about a x b).
    Turning a camera's axes this way between successive view directions is parallel transport:
    the camera does not spin about its viewing axis."""
    axis = cross3(a, b)  # [3] sin(angle) * unit axis
    c = float(a @ b)
    if c < -1.0 + 1e-12:  # antipodal: half a turn about a fixed perpendicular
        p = perpendicular(a)
        return 2.0 * (p @ v) * p - v
    return v + cross3(axis, v) + cross3(axis, cross3(axis, v)) / (1.0 + c)
