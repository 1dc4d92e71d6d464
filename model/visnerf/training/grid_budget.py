"""The final grid a time budget can fill: at most the rays the run will see over ``rays_per_voxel``.

A step's samples grow with the grid (one every ``step_ratio`` voxels along a ray), so the rays a
second at ``n`` voxels a side are those measured at the grid ``now`` times ``now / n``. The rays
the run will see at a final grid of ``n`` are those seen so far and those the remaining seconds
give at ``n``; the grid's ``n^3`` voxels may hold at most that over ``rays_per_voxel``. The largest
such ``n`` is the root of an increasing function, found by bisection.
"""

import math
from dataclasses import dataclass

BISECTIONS = 60
"""Halvings of the bracket: far below one voxel for any grid a run can hold."""


@dataclass(frozen=True)
class GridBudget:
    """What a run has measured at an upsampling: rays seen, rays a second at the grid it holds
    (``now`` voxels a side, the cube root of the count) and training seconds left."""

    seen_rays: float
    rays_per_second: float
    now: float
    seconds_left: float

    def rays_at(self, n: float) -> float:
        """Rays the whole run will have seen with a final grid of ``n`` voxels a side."""
        return self.seen_rays + self.rays_per_second * (self.now / n) * max(self.seconds_left, 0.0)

    def largest_grid(self, rays_per_voxel: float, ceiling: float) -> float:
        """Voxels a side, in ``[now, ceiling]``, of the largest grid whose voxels are at most
        ``rays_at(n) / rays_per_voxel``: ``now`` where even that grid holds more, ``ceiling``
        where that one holds fewer."""
        if not (rays_per_voxel > 0 and math.isfinite(rays_per_voxel)):
            raise ValueError(f"rays_per_voxel must be a finite number above 0, got {rays_per_voxel!r}")
        values = (self.seen_rays, self.rays_per_second, self.now, self.seconds_left, ceiling)
        if not all(math.isfinite(v) for v in values) or min(self.seen_rays, self.rays_per_second) < 0 or self.now <= 0:
            raise ValueError(f"a grid budget needs finite measures, rays and grids >= 0, got {self}")
        lo, hi = self.now, max(self.now, ceiling)

        def fits(n: float) -> bool:
            return n**3 * rays_per_voxel <= self.rays_at(n)

        if fits(hi):
            return hi
        if not fits(lo):
            return lo
        for _ in range(BISECTIONS):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if fits(mid) else (lo, mid)
        return lo

    def describe(self, final: float, rays_per_voxel: float) -> str:
        return (f"{self.rays_per_second:,.0f} rays a second at {self.now:.0f} voxels a side and "
                f"{self.seconds_left:.0f} s left: about {self.rays_at(final) / 1e6:.1f} M rays in the run, "
                f"so at most {final:.0f} voxels a side at {rays_per_voxel:g} rays a voxel")
