"""Jumping over empty space along rays (inference).

``EmptySpace`` holds, for every cell of the occupancy grid, the Chebyshev distance in cells to
the nearest occupied cell (0 for an occupied cell), capped at ``max_distance``. A point in a cell
at distance k >= 1 lies in a block of (2k - 1)^3 empty cells centred on its cell, so a ray may
jump to where it leaves that block without passing an occupied cell.

``sample_window`` uses that from both ends of every ray: it finds the first and the last sample
of the marching lattice (``t_near + step * (i + 0.5)``) that lie in an occupied cell, and the
march walks only that window. Every sample left out lies in an empty cell, which the march would
have skipped anyway, so the frame is the same; what is saved is generating and testing those
samples (on the bundled scenes and Nyx, 1.2x to 4.6x fewer samples to walk).
"""

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float, Int, UInt8
from torch import Tensor

MAX_DISTANCE = 16
"""Distances are counted up to this many cells; farther cells hold this value."""
MAX_JUMPS = 24
"""Jumps per ray and direction; a ray that needs more starts its walk where the jumps ended."""
_GUARD = 1e-3
"""Lattice steps kept before the edge of an empty block, so float rounding never skips a sample
that a hair's breadth lies in the next (occupied) cell."""


def distance_to_content(grid: Bool[Tensor, "x y z"], max_distance: int = MAX_DISTANCE) -> Int[Tensor, "x y z"]:
    """Chebyshev distance in cells from every cell to the nearest occupied one, capped at
    ``max_distance`` (also where nothing is occupied)."""
    reached = grid.float()[None, None]
    dist = torch.full(grid.shape, max_distance, dtype=torch.int16, device=grid.device)
    dist[grid] = 0
    for k in range(1, max_distance):
        grown = F.max_pool3d(reached, kernel_size=3, stride=1, padding=1)
        new = (grown > reached)[0, 0]
        if not bool(new.any()):
            break
        dist[new] = k
        reached = grown
    return dist


@dataclass(frozen=True)
class EmptySpace:
    """The occupancy grid over ``aabb`` with each cell's distance to content.

    Lookups gather with ``index_select`` from small flat tables (uint8): advanced indexing is
    several times slower on the CPU.
    """

    occupied: UInt8[Tensor, " cells"]
    """Flattened occupancy (x-major), 0 or 1, uint8."""
    distance: UInt8[Tensor, " cells"]
    """Flattened ``distance_to_content``, uint8."""
    shape: tuple[int, int, int]
    lower: Float[Tensor, " 3"]
    cells_per_unit: Float[Tensor, " 3"]
    """Cells per world unit along each axis."""
    last_cell: Float[Tensor, " 3"]
    strides: Float[Tensor, " 3"]
    """Flat-index strides as floats (exact: the grids hold far fewer than 2^24 cells)."""

    @classmethod
    def of(cls, grid: Bool[Tensor, "x y z"], aabb: Float[Tensor, "2 3"]) -> "EmptySpace":
        shape = tuple(int(s) for s in grid.shape)
        res = torch.tensor(shape, dtype=aabb.dtype, device=aabb.device)
        extent = (aabb[1] - aabb[0]).clamp_min(torch.finfo(aabb.dtype).eps)
        strides = torch.tensor([shape[1] * shape[2], shape[2], 1], dtype=aabb.dtype, device=aabb.device)
        return cls(
            occupied=grid.reshape(-1).to(torch.uint8).contiguous(),
            distance=distance_to_content(grid).reshape(-1).to(torch.uint8).contiguous(),
            shape=shape,  # type: ignore[arg-type]
            lower=aabb[0].clone(),
            cells_per_unit=res / extent,
            last_cell=res - 1.0,
            strides=strides,
        )

    def min_cell_size(self) -> float:
        """World size of the smallest cell edge."""
        return float((1.0 / self.cells_per_unit).min())

    def cell_coords(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, "n 3"]:
        """Continuous cell coordinates: cell ``(i, j, k)`` spans ``[i, i + 1) x ...``."""
        return (points - self.lower) * self.cells_per_unit

    def cell_index(self, cells: Float[Tensor, "n 3"]) -> Int[Tensor, " n"]:
        """Flat index of the cell holding each continuous cell coordinate, clamped to the grid
        (a point a rounding error outside the box reads the border cell)."""
        whole = torch.minimum(cells.floor().clamp_(min=0.0), self.last_cell)
        return (whole @ self.strides).long()

    def occupied_at(self, points: Float[Tensor, "n 3"]) -> Bool[Tensor, " n"]:
        return self.occupied.index_select(0, self.cell_index(self.cell_coords(points))).bool()

    def _jump(
        self, points: Float[Tensor, "n 3"], directions: Float[Tensor, "n 3"], backwards: bool, near: int
    ) -> tuple[Bool[Tensor, " n"], Float[Tensor, " n"]]:
        """For each point: whether its cell lies within ``near`` cells of an occupied one, and
        else the ray distance (along ``directions``, or against them when ``backwards``) to the
        edge of the block of cells that do not."""
        cells = self.cell_coords(points)
        k = self.distance.index_select(0, self.cell_index(cells))  # [n]
        cell = cells.floor()
        velocity = (-directions if backwards else directions) * self.cells_per_unit  # cells per unit t
        # cells within k - 1 - near of this one are more than ``near`` cells from content
        reach = (k.to(cells.dtype) - 1.0 - near)[:, None]
        # the block spans [cell - reach, cell + 1 + reach) per axis
        gap = torch.where(velocity > 0, cell + 1.0 + reach - cells, cells - cell + reach)  # >= reach >= 0
        speed = velocity.abs()
        exit_t = torch.where(speed > 0, gap / speed, torch.inf)  # never 0 / 0 on an axis the ray does not move along
        return k <= near, exit_t.amin(dim=-1)

    def sample_window(
        self,
        rays_o: Float[Tensor, "n 3"],
        rays_d: Float[Tensor, "n 3"],
        t_near: Float[Tensor, " n"],
        step: float,
        first: Int[Tensor, " n"],
        last: Int[Tensor, " n"],
        near: int = 0,
    ) -> tuple[Int[Tensor, " n"], Int[Tensor, " n"]]:
        """Shrink each ray's window ``[first, last]`` of lattice samples to the first and the last
        sample in an occupied cell (``near = 1``: in a cell within one cell of an occupied one).
        A ray with no such sample gets ``first > last``.

        ``near = 1`` serves stratified training samples: a sample moved by at most half a step
        from its lattice point, with the step no larger than a cell, lies in the lattice point's
        cell or a neighbour, so every such sample in an occupied cell has its lattice point in
        the window."""
        first = self._walk(rays_o, rays_d, t_near, step, first, last, backwards=False, near=near)
        last = self._walk(rays_o, rays_d, t_near, step, last, first, backwards=True, near=near)
        return first, last

    def _walk(
        self,
        rays_o: Tensor,
        rays_d: Tensor,
        t_near: Tensor,
        step: float,
        start: Tensor,
        bound: Tensor,
        backwards: bool,
        near: int,
    ) -> Tensor:
        """Move each ray's sample index from ``start`` towards ``bound`` past samples in empty
        blocks; returns the first index in a cell within ``near`` cells of an occupied one, an
        index past ``bound`` when there is none, or where the jumps ran out."""
        index = start.clone()
        rays = ((start >= bound) if backwards else (start <= bound)).nonzero()[:, 0]
        o, d, tn, i, b = (x.index_select(0, rays) for x in (rays_o, rays_d, t_near, start, bound))
        for _ in range(MAX_JUMPS):
            if rays.numel() == 0:
                break
            t = tn + step * (i.to(tn.dtype) + 0.5)
            occupied, exit_t = self._jump(o + d * t[:, None], d, backwards, near)
            if backwards:
                # the last lattice sample at or before the block's near edge, and at least one back
                target = torch.floor((t - exit_t - tn) / step - 0.5 + _GUARD)
                nxt = torch.minimum(target.clamp_min(-1.0).long(), i - 1)
                going = ~occupied & (nxt >= b)
            else:
                target = torch.ceil((t + exit_t - tn) / step - 0.5 - _GUARD)
                nxt = torch.maximum(target.clamp_max(float(2**40)).long(), i + 1)
                going = ~occupied & (nxt <= b)
            nxt = torch.where(occupied, i, nxt)
            index.index_copy_(0, rays, nxt)
            keep = going.nonzero()[:, 0]
            if keep.numel() == rays.numel():
                i = nxt
                continue
            rays, o, d, tn, b = (x.index_select(0, keep) for x in (rays, o, d, tn, b))
            i = nxt.index_select(0, keep)
        return index
