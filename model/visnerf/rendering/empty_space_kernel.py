"""The empty-space walk of ``EmptySpace.sample_window`` as one compiled loop per ray (CPU, numba).

The torch walk (``EmptySpace.walk``) moves every ray one jump per round in a batch: about twenty
small tensor operations a round for up to ``MAX_JUMPS`` rounds, a fixed cost that dominated the
walk. Here each ray walks from its first sample up and from its last sample down, the two walks
taking turns in one plain loop, with the same arithmetic in float32 (the cell of a lattice sample
is computed exactly as ``EmptySpace.occupied_at`` does), and without a cap on the jumps: every
ray's window ends at its first and last sample in a cell within ``near`` cells of an occupied one,
which the torch walk reaches only when its jumps do not run out. The loop releases the GIL.
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
def _flat_cell(cells, last_cell, strides):
    """Flat index of the cell holding continuous cell coordinates ``cells`` (a 3-tuple), clamped
    to the grid: ``EmptySpace.cell_index`` in the compiled loops (the walk and ``march_kernel``).
    Floored and clamped in float32, as there (``math.floor`` gives an integer, and the mixed
    comparisons after it cost a placing loop half its time)."""
    zero = np.float32(0.0)
    x = min(max(np.floor(cells[0]), zero), last_cell[0])
    y = min(max(np.floor(cells[1]), zero), last_cell[1])
    z = min(max(np.floor(cells[2]), zero), last_cell[2])
    return int(x) * strides[0] + int(y) * strides[1] + int(z) * strides[2]


WALKING, FOUND, LEFT = 0, 1, 2
"""What one probe of a walk finds: go on from the next index, this index is near content, or the
ray leaves the grid (or its path is not finite) before any."""


@no_type_check
def _probe(o, d, tn, step, inv_step, inv_speed, u, sign, near, distance, lower, cpu, last_cell, strides):
    """One probe of a walk at lattice index ``sign * u`` (``u`` grows): ``(FOUND, u)`` where its
    cell is within ``near`` cells of content, else ``(WALKING, next u)`` past the cells that are not,
    or ``(LEFT, u)``. ``inv_speed[a]``: cells crossed per unit of ``t`` along axis ``a``, inverted
    (0 where the ray does not move along it)."""
    f32 = np.float32
    one = f32(1.0)
    t = tn + step * (f32(sign * u) + f32(0.5))
    c0 = (o[0] + d[0] * t - lower[0]) * cpu[0]
    c1 = (o[1] + d[1] * t - lower[1]) * cpu[1]
    c2 = (o[2] + d[2] * t - lower[2]) * cpu[2]
    cells = (c0, c1, c2)
    k = distance[flat_cell(cells, last_cell, strides)]
    if k <= near:
        return FOUND, u
    reach = f32(k) - one - f32(near)
    exit_t = f32(np.inf)
    for a in range(3):
        if inv_speed[a] > 0:
            cell = np.floor(cells[a])
            if d[a] * f32(sign) > 0:
                gap = cell + one + reach - cells[a]
            else:
                gap = cells[a] - cell + reach
            exit_t = min(exit_t, gap * inv_speed[a])
    jump = f32(u) + exit_t * inv_step - f32(GUARD)
    if not jump < f32(2.0**40):
        return LEFT, u
    return WALKING, max(math.ceil(jump), u + 1)  # at least one sample on


@no_type_check
def _windows(rays_o, rays_d, t_near, step64, first, last, near, distance, lower, cpu, last_cell, strides,
             out_first, out_last):
    """Each ray's window ``[first, last]`` narrowed to its samples near content (``first > last``:
    none) into ``out_first``, ``out_last``. The walk up from ``first`` and the walk down from
    ``last`` take turns in one loop: each probe waits on the one before it, and two independent
    walks let the core overlap them. The walk down stops at the sample the walk up found."""
    f32 = np.float32
    step = f32(step64)
    inv_step = f32(1.0) / step
    inv_speed = np.empty(3, f32)
    for r in range(rays_o.shape[0]):
        lo, hi = first[r], last[r]
        if lo > hi:
            out_first[r], out_last[r] = lo, hi
            continue
        o, d, tn = rays_o[r], rays_d[r], t_near[r]
        for a in range(3):
            speed = abs(d[a] * cpu[a])
            inv_speed[a] = f32(1.0) / speed if speed > 0 else f32(0.0)
        up, down = lo, -hi  # the walk down counts ``-index`` up to ``down_bound``
        down_bound = -lo
        up_state, down_state = WALKING, WALKING
        while up_state == WALKING or down_state == WALKING:
            if up_state == WALKING:
                up_state, nxt = probe(o, d, tn, step, inv_step, inv_speed, up, 1, near, distance, lower, cpu,
                                      last_cell, strides)
                if up_state == FOUND:
                    down_bound = -up
                elif up_state == LEFT or nxt > hi:  # nothing near content: an empty window
                    up = hi + 1 if up_state == LEFT else nxt
                    up_state = LEFT
                    break
                else:
                    up = nxt
            if down_state == WALKING:
                if down > down_bound:
                    down_state = LEFT
                else:
                    down_state, nxt = probe(o, d, tn, step, inv_step, inv_speed, down, -1, near, distance, lower, cpu,
                                            last_cell, strides)
                    if down_state == WALKING:
                        down = nxt
        out_first[r] = up
        if up_state == LEFT:
            out_last[r] = hi
        elif down_state == LEFT:  # the walk down passed the walk up's sample (float rounding): empty
            out_last[r] = up - 1
        else:
            out_last[r] = -down


flat_cell = compiled.jit(_flat_cell, inline=True)
probe = compiled.jit(_probe, inline=True)
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
    arrays = [t.detach().contiguous().numpy()
              for t in (rays_o.float(), rays_d.float(), t_near.float(), first.long(), last.long())]
    tables = grid.arrays()
    of, ol = out_first.numpy(), out_last.numpy()
    for start in range(0, n, RAYS_PER_CALL):
        raise_if_cancelled(cancel)
        rays = min(n, start + RAYS_PER_CALL) - start

        def part(a: int, b: int, start: int = start) -> None:
            sl = slice(start + a, start + b)
            _compiled(*(x[sl] for x in arrays[:3]), step, *(x[sl] for x in arrays[3:]), int(near), *tables,
                      of[sl], ol[sl])

        compiled.run_ranges(part, rays, RAYS_PER_PART)
    return out_first.to(first.dtype), out_last.to(last.dtype)
