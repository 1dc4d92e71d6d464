"""Where each evaluated frame sits in parameter space, relative to the training values.

- ``at_training_values``: every parameter equals one of its axis' training values (within a
  tolerance of ``TOLERANCE`` of the local spacing); otherwise the frame lies between them, which is
  where the model interpolates.
- ``offset``: the largest distance of any parameter to its nearest training value, in units of the
  local spacing of that axis (0 at a training value, 0.5 midway between two).
- ``motion`` (read along the split's frame order, as on the paper's test path): an axis moves at a
  frame when its value differs from the previous frame's (the first frame compares with the next).
  ``one``: exactly one axis moves; ``all``: every axis moves (K >= 2); ``some``: more than one but
  not all; ``none``: no parameter moves (only the camera), and always for a static scene. On the
  paper's 181-view path this gives its 90 one-at-a-time and 91 all-moving frames.
"""

from dataclasses import dataclass
from typing import Literal

import numpy as np
from jaxtyping import Float

from visnerf.checkpoint import ParamAxis

TOLERANCE = 1e-3
"""Fraction of the local spacing within which a value counts as a training value."""

Motion = Literal["none", "one", "some", "all"]


@dataclass(frozen=True)
class Placement:
    """One frame's position in parameter space."""

    at_training_values: bool
    offset: float
    """Largest distance to the nearest training value, in local spacings (0 .. 0.5)."""
    n_moving: int
    """Axes whose value changed from the previous frame."""
    motion: Motion


def spacing_offset(axis: ParamAxis, value: int | float) -> float:
    """Distance of ``value`` to the nearest training value of ``axis``, in local spacings."""
    knots = np.asarray(axis.values, dtype=np.float64)
    if knots.size < 2:
        return 0.0
    k = int(np.clip(np.searchsorted(knots, value) - 1, 0, knots.size - 2))
    spacing = float(knots[k + 1] - knots[k])
    nearest = float(np.min(np.abs(knots - value)))
    return nearest / spacing if spacing > 0 else 0.0


def moving_axes(params: Float[np.ndarray, "n k"]) -> np.ndarray:
    """Bool [n, k]: whether each axis' value differs from the previous frame's (the first: the next's)."""
    n, k = params.shape
    if n < 2 or k == 0:
        return np.zeros((n, k), dtype=bool)
    scale = np.maximum(np.abs(params).max(axis=0), 1.0)
    changed = np.abs(np.diff(params, axis=0)) > 1e-9 * scale  # [n - 1, k]
    return np.concatenate([changed[:1], changed], axis=0)


def classify(axes: tuple[ParamAxis, ...], params: Float[np.ndarray, "n k"]) -> list[Placement]:
    """Placement of every frame of a split (``params`` raw values in ``axes`` order)."""
    moving = moving_axes(params)
    k = len(axes)
    out = []
    for i in range(params.shape[0]):
        offsets = [spacing_offset(axis, float(params[i, j])) for j, axis in enumerate(axes)]
        n_moving = int(moving[i].sum())
        motion: Motion
        if n_moving == 0:
            motion = "none"
        elif n_moving == 1:
            motion = "one"
        elif n_moving == k:
            motion = "all"
        else:
            motion = "some"
        out.append(
            Placement(
                at_training_values=all(o <= TOLERANCE for o in offsets),
                offset=float(max(offsets, default=0.0)),
                n_moving=n_moving,
                motion=motion,
            )
        )
    return out
