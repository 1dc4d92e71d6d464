"""``HoldoutConfig``: which training frames are held out for validation."""

import math
import numbers
from dataclasses import dataclass, field

from visnerf.config.checks import (
    is_whole,
    require,
)


@dataclass(frozen=True)
class HoldoutConfig:
    """Which training frames are held out for validation."""

    views: tuple[int, ...] = ()
    """Indices of views (position in the icosphere order) held out at every parameter setting."""
    settings: tuple[tuple[float, ...], ...] = field(default_factory=tuple)
    """Whole parameter settings held out from all views."""
    axis_values: tuple[tuple[int, float], ...] = field(default_factory=tuple)
    """``(axis, value)`` pairs: every frame whose parameter ``axis`` (index among the dataset's
    varying parameters, in their order) has ``value`` is held out, at all views and all values of
    the other axes. Holding out an axis' middle value leaves training only the values around it, so
    validation measures the model between sampled values, as a test path between them does."""

    def __post_init__(self) -> None:
        for view in self.views:
            require(is_whole(view) and view >= 0,
                     f"held-out view {view!r} must be a whole number of at least 0")
        for pair in self.axis_values:
            require(isinstance(pair, tuple) and len(pair) == 2,
                     f"held-out axis value {pair!r} must be a pair (axis index, value)")
            axis, value = pair
            require(is_whole(axis) and axis >= 0,
                     f"held-out axis value {pair!r}: the axis must be an index of at least 0, got {axis!r}")
            require(isinstance(value, numbers.Real) and math.isfinite(value),
                     f"held-out axis value {pair!r}: the value must be a finite number, got {value!r}")
