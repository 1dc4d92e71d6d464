"""The grid priors of the fused step, applied at the rows a step touched (lazy, as its Adam is).

(``l1_coefficients`` gives the optimizer the L1 prior to add as it updates rows from pending taps,
``training.sparse_adam``; the functions below add a prior into a materialized gradient.)

``regularizers.add_grid_l1_`` and ``add_grid_total_variation_`` add their gradient into every row
of a VM grid's tables: a pass over the whole table each step, and a gradient on every row, which
would make the row-sparse optimizer (``sparse_adam``) update every row. Here the same gradient is
added only at the rows whose mark is set (``vm_rows.RowGradients``): the rows the step's samples
read. At those rows it is the dense prior's gradient exactly (tested); a row no sample reads is
left as it is, as lazy Adam leaves it. Returns the part of each term at those rows.
"""

from typing import no_type_check

import numpy as np

from visnerf import compiled
from visnerf.representation.table_gradients import MIN_ROWS_A_PART, RowGradients, TableGradient
from visnerf.representation.vm import VMGrid
from visnerf.representation.vm_kernel import table_layout
from visnerf.representation.vm_taps import MODES


@no_type_check  # compiled by numba
def _l1(table, grad, marks, starts, coefficients, totals, first, stop):
    """``grad += c_part * sign(table)`` at marked rows ``first <= row < stop`` (row ``i`` is in part
    ``p`` where ``starts[p] <= i < starts[p + 1]``); ``totals[row] = c_part * sum |table[row]|``."""
    for part in range(starts.shape[0] - 1):
        c = coefficients[part]
        for row in range(max(first, starts[part]), min(stop, starts[part + 1])):
            if marks[row] == 0:
                continue
            part_sum = 0.0
            for ch in range(table.shape[1]):
                v = table[row, ch]
                grad[row, ch] += c * ((v > 0) - (v < 0))
                part_sum += abs(v)
            totals[row] = c * part_sum


@no_type_check
def _tv_plane(table, grad, marks, start, h, w, scale_y, scale_x, totals, y_first, y_stop):
    """The gradient of ``scale_y * sum (v[y+1, x] - v[y, x])^2 + scale_x * sum (v[y, x+1] - v[y, x])^2``
    of one plane (rows ``start + y * w + x``) added at its marked rows of lines
    ``y_first <= y < y_stop``; ``totals[y]``: the terms of line ``y``'s differences whose lower row
    is marked. A marked row's gradient is written by its own line alone.

    A neighbour outside the plane is read as the row itself (a difference of 0, which adds 0), so
    the channel loop has no branch; the terms are summed per channel, then over the channels, so
    that the channels' additions do not wait on one another (one running total waited on each)."""
    c = table.shape[1]
    sums = np.zeros(c, np.float64)
    for y in range(y_first, y_stop):
        sums[:] = 0.0
        for x in range(w):
            row = start + y * w + x
            if marks[row] == 0:
                continue
            up = row - w if y > 0 else row
            down = row + w if y < h - 1 else row
            left = row - 1 if x > 0 else row
            right = row + 1 if x < w - 1 else row
            for ch in range(c):
                v = table[row, ch]
                d_down = table[down, ch] - v
                d_right = table[right, ch] - v
                g = 2.0 * scale_y * (v - table[up, ch])
                g -= 2.0 * scale_y * d_down
                g += 2.0 * scale_x * (v - table[left, ch])
                g -= 2.0 * scale_x * d_right
                grad[row, ch] += g
                sums[ch] += scale_y * d_down * d_down + scale_x * d_right * d_right
        total = 0.0
        for ch in range(c):
            total += sums[ch]
        totals[y] = total


_l1_loop = compiled.jit(_l1, fastmath={"reassoc"})  # a row's sum of |value| in vector lanes
_tv_plane_loop = compiled.jit(_tv_plane)


def l1_coefficients(table: TableGradient, weight: float) -> np.ndarray:
    """Per mode, the (sub)gradient coefficient of ``regularizers.add_grid_l1_`` on ``table``'s rows:
    ``weight / (6 * values in that mode's factor)``."""
    starts = table.part_starts
    c = table.table.shape[1]
    return np.array([weight / (2 * len(MODES) * (starts[p + 1] - starts[p]) * c) for p in range(len(MODES))])


def add_l1_at_marks(grid: VMGrid, grads: RowGradients, weight: float) -> float:
    """``regularizers.add_grid_l1_`` at the marked rows: ``weight * mean |v|`` of each of the six
    factors, averaged, its (sub)gradient added where a row is marked (ranges of rows on every
    thread; the value summed row by row in order, the same on any thread count)."""
    total = 0.0
    for table in grads.tables():
        n = table.n_rows
        totals = np.zeros(n, np.float64)
        arrays = (table.table.detach().numpy(), table.buffer().numpy(), table.marks, table.part_starts.astype(np.int64),
                  l1_coefficients(table, weight), totals)
        compiled.run_ranges(lambda a, b, arrays=arrays: _l1_loop(*arrays, a, b), n, MIN_ROWS_A_PART)
        total += float(totals.sum())
    return total


def _tv_at_marks(table: np.ndarray, grad: np.ndarray, marks: np.ndarray, start: int, h: int, w: int,
                 scale_y: float, scale_x: float) -> float:
    """``_tv_plane`` over all ``h`` lines of one plane, bands of lines on every thread; the value
    summed line by line in order, so the same on any thread count."""
    totals = np.zeros(h, np.float64)
    lines_a_band = -(-MIN_ROWS_A_PART // w)  # bands of at least MIN_ROWS_A_PART rows
    compiled.run_ranges(lambda a, b: _tv_plane_loop(table, grad, marks, start, h, w, scale_y, scale_x, totals, a, b),
                        h, lines_a_band)
    return float(totals.sum())


def add_total_variation_at_marks(grid: VMGrid, grads: RowGradients, weight: float) -> float:
    """``regularizers.add_grid_total_variation_`` at the marked rows."""
    planes, lines = grid.row_tables()
    res, plane_off, line_off = table_layout(grid.resolution, planes.shape[0], lines.shape[0])
    c = planes.shape[1]
    scale = weight / len(MODES)
    total = 0.0
    table, grad = planes.detach().numpy(), grads.plane.buffer().numpy()
    for i, ((a, b), _) in enumerate(MODES):
        w, h = int(res[a]), int(res[b])
        scale_y = scale / max(1, (h - 1) * w * c) if h > 1 else 0.0
        scale_x = scale / max(1, h * (w - 1) * c) if w > 1 else 0.0
        total += _tv_at_marks(table, grad, grads.plane.marks, int(plane_off[i]), h, w, scale_y, scale_x)
    table, grad = lines.detach().numpy(), grads.line.buffer().numpy()
    for i, (_, axis) in enumerate(MODES):
        n = int(res[axis])
        scale_y = scale / max(1, (n - 1) * c) if n > 1 else 0.0
        total += _tv_at_marks(table, grad, grads.line.marks, int(line_off[i]), n, 1, scale_y, 0.0)
    return total
