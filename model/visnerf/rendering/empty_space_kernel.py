"""The empty-space walk of ``EmptySpace.sample_window`` as one compiled loop per ray (CPU, numba).

The torch walk (``EmptySpace.walk``) moves every ray one jump per round in a batch: about twenty
small tensor operations a round for up to ``MAX_JUMPS`` rounds, a fixed cost that dominated the
walk. Here each ray walks from its first sample up and from its last sample down in plain loops,
with the same arithmetic in float32 (the cell of a lattice sample is computed exactly as
``EmptySpace.occupied_at`` does), and without a cap on the jumps: every ray's window ends at its
first and last sample in a cell within ``near`` cells of an occupied one, which the torch walk
reaches only when its jumps do not run out. The loop releases the GIL.
"""

import math
from dataclasses import dataclass
from typing import no_type_check

import numpy as np
import torch
from jaxtyping import Float, Int, UInt8
from torch import Tensor

from visnerf import compiled
from visnerf.rendering.cancel import CancelCheck, raise_if_cancelled

GUARD = 1e-3
"""Lattice steps kept before the edge of an empty block, so float rounding never skips a sample
that a hair's breadth lies in the next (occupied) cell (both walks)."""
RAYS_PER_CALL = 16384
"""Rays walked between two cancel checks."""
RAYS_PER_PART = 256
"""The fewest rays a thread walks on its own (``compiled.parts``): a training step's rays are
walked on every core, a frame's chunks each on one (the renderer's threads run one torch thread)."""


def available(device: torch.device) -> bool:
    """Whether the compiled walk serves ``device`` (``compiled.serves``)."""
    return compiled.serves(device)


@no_type_check  # compiled by numba
def _flat_cell(cells, last_cell, strides):  # noqa: ANN001, ANN202
    """Flat index of the cell holding continuous cell coordinates ``cells`` (a 3-tuple), clamped
    to the grid: ``EmptySpace.cell_index`` in the compiled loops (the walk and ``march_kernel``).
    Floored and clamped in float32, as there (``math.floor`` gives an integer, and the mixed
    comparisons after it cost a placing loop half its time)."""
    zero = np.float32(0.0)
    x = min(max(np.floor(cells[0]), zero), last_cell[0])
    y = min(max(np.floor(cells[1]), zero), last_cell[1])
    z = min(max(np.floor(cells[2]), zero), last_cell[2])
    return int(x) * strides[0] + int(y) * strides[1] + int(z) * strides[2]


@no_type_check
def _first_near(o, d, tn, step, u, bound, sign, near, distance, lower, cpu, last_cell, strides):  # noqa: ANN001, ANN202
    """From lattice index ``sign * u`` (``u`` grows), the first index whose cell is within
    ``near`` cells of content, or an index past ``sign * bound`` where there is none."""
    f32 = np.float32
    one = f32(1.0)
    while u <= bound:
        t = tn + step * (f32(sign * u) + f32(0.5))
        exit_t = f32(np.inf)
        c0 = (o[0] + d[0] * t - lower[0]) * cpu[0]
        c1 = (o[1] + d[1] * t - lower[1]) * cpu[1]
        c2 = (o[2] + d[2] * t - lower[2]) * cpu[2]
        cells = (c0, c1, c2)
        k = distance[flat_cell(cells, last_cell, strides)]
        if k <= near:
            return sign * u
        reach = f32(k) - one - f32(near)
        for a in range(3):
            vel = d[a] * f32(sign) * cpu[a]
            cell = np.floor(cells[a])
            if vel > 0:
                gap = cell + one + reach - cells[a]
            else:
                gap = cells[a] - cell + reach
            speed = abs(vel)
            if speed > 0:
                exit_t = min(exit_t, gap / speed)
        jump = f32(u) + exit_t / step - f32(GUARD)
        if not jump < f32(2.0**40):  # the ray leaves the grid along its path (or is not finite)
            return sign * (bound + 1)
        u = max(math.ceil(jump), u + 1)  # at least one sample on
    return sign * u


@no_type_check
def _windows(rays_o, rays_d, t_near, step64, first, last, near, distance, lower, cpu, last_cell, strides,  # noqa: ANN001, ANN202
             out_first, out_last):
    """Each ray's window ``[first, last]`` narrowed to its samples near content (``first > last``:
    none) into ``out_first``, ``out_last``."""
    step = np.float32(step64)
    for r in range(rays_o.shape[0]):
        lo, hi = first[r], last[r]
        if lo > hi:
            out_first[r], out_last[r] = lo, hi
            continue
        o, d, tn = rays_o[r], rays_d[r], t_near[r]
        a = first_near(o, d, tn, step, lo, hi, 1, near, distance, lower, cpu, last_cell, strides)
        if a > hi:  # nothing near content: an empty window
            out_first[r], out_last[r] = a, hi
            continue
        # down from the last sample; the walk up found content, so this one stops at or above ``a``
        b = first_near(o, d, tn, step, -hi, -a, -1, near, distance, lower, cpu, last_cell, strides)
        out_first[r], out_last[r] = a, b


flat_cell = compiled.jit(_flat_cell, inline=True)
first_near = compiled.jit(_first_near, inline=True)
_compiled = compiled.jit(_windows)


@dataclass(frozen=True)
class GridTables:
    """A table of ``EmptySpace``'s cells (its distances, or its occupancy) and the cell geometry,
    as the compiled loops read them (``arrays``)."""

    cells: UInt8[Tensor, " cells"]
    lower: Float[Tensor, " 3"]
    cells_per_unit: Float[Tensor, " 3"]
    last_cell: Float[Tensor, " 3"]
    strides: Float[Tensor, " 3"]

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(cells uint8, lower, cells per unit, last cell as float32, flat strides as int64)."""
        return (self.cells.contiguous().numpy(),
                *(t.float().contiguous().numpy() for t in (self.lower, self.cells_per_unit, self.last_cell)),
                np.asarray([int(s) for s in self.strides.tolist()], np.int64))


def sample_windows(
    grid: GridTables,
    rays_o: Float[Tensor, "n 3"],
    rays_d: Float[Tensor, "n 3"],
    t_near: Float[Tensor, " n"],
    step: float,
    first: Int[Tensor, " n"],
    last: Int[Tensor, " n"],
    near: int,
    cancel: CancelCheck | None = None,
) -> tuple[Int[Tensor, " n"], Int[Tensor, " n"]]:
    """``EmptySpace.sample_window`` on the CPU (``grid`` holds its distances), asking ``cancel``
    between calls of ``RAYS_PER_CALL`` rays, each call shared by the threads (``RAYS_PER_PART``)."""
    if compiled.numba is None:  # pragma: no cover
        raise RuntimeError("numba is not installed: the compiled empty-space walk is unavailable")
    n = first.shape[0]
    out_first, out_last = torch.empty(n, dtype=torch.int64), torch.empty(n, dtype=torch.int64)
    arrays = [t.detach().contiguous().numpy() for t in (rays_o.float(), rays_d.float(), t_near.float(), first.long(), last.long())]
    tables = grid.arrays()
    of, ol = out_first.numpy(), out_last.numpy()
    for start in range(0, n, RAYS_PER_CALL):
        raise_if_cancelled(cancel)
        rays = min(n, start + RAYS_PER_CALL) - start

        def part(a: int, b: int, start: int = start) -> None:
            sl = slice(start + a, start + b)
            _compiled(*(x[sl] for x in arrays[:3]), step, *(x[sl] for x in arrays[3:]), int(near), *tables, of[sl], ol[sl])

        compiled.run_ranges(part, rays, RAYS_PER_PART)
    return out_first.to(first.dtype), out_last.to(last.dtype)
