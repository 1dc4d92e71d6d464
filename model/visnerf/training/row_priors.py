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
from visnerf.representation.table_gradients import RowGradients, TableGradient
from visnerf.representation.vm import VMGrid
from visnerf.representation.vm_kernel import table_layout
from visnerf.representation.vm_taps import MODES


@no_type_check  # compiled by numba
def _l1(table, grad, marks, starts, coefficients):  # noqa: ANN001, ANN202
    """``grad += c_part * sign(table)`` at marked rows (row ``i`` in part ``p`` where
    ``starts[p] <= i < starts[p + 1]``); returns ``sum c_part |table|`` over them."""
    total = 0.0
    for part in range(starts.shape[0] - 1):
        c = coefficients[part]
        for row in range(starts[part], starts[part + 1]):
            if marks[row] == 0:
                continue
            part_sum = 0.0
            for ch in range(table.shape[1]):
                v = table[row, ch]
                grad[row, ch] += c * ((v > 0) - (v < 0))
                part_sum += abs(v)
            total += c * part_sum
    return total


@no_type_check
def _tv_plane(table, grad, marks, start, h, w, scale_y, scale_x):  # noqa: ANN001, ANN202
    """The gradient of ``scale_y * sum (v[y+1, x] - v[y, x])^2 + scale_x * sum (v[y, x+1] - v[y, x])^2``
    of one plane (rows ``start + y * w + x``) added at its marked rows; returns the terms of the
    differences whose lower row is marked."""
    total = 0.0
    for y in range(h):
        for x in range(w):
            row = start + y * w + x
            if marks[row] == 0:
                continue
            for ch in range(table.shape[1]):
                v = table[row, ch]
                g = 0.0
                if y > 0:
                    g += 2.0 * scale_y * (v - table[row - w, ch])
                if y < h - 1:
                    d = table[row + w, ch] - v
                    g -= 2.0 * scale_y * d
                    total += scale_y * d * d
                if x > 0:
                    g += 2.0 * scale_x * (v - table[row - 1, ch])
                if x < w - 1:
                    d = table[row + 1, ch] - v
                    g -= 2.0 * scale_x * d
                    total += scale_x * d * d
                grad[row, ch] += g
    return total


_l1_loop = compiled.jit(_l1)
_tv_plane_loop = compiled.jit(_tv_plane)


def l1_coefficients(table: TableGradient, weight: float) -> np.ndarray:
    """Per mode, the (sub)gradient coefficient of ``regularizers.add_grid_l1_`` on ``table``'s rows:
    ``weight / (6 * values in that mode's factor)``."""
    starts = table.part_starts
    c = table.table.shape[1]
    return np.array([weight / (2 * len(MODES) * (starts[p + 1] - starts[p]) * c) for p in range(len(MODES))])


def add_l1_at_marks(grid: VMGrid, grads: RowGradients, weight: float) -> float:
    """``regularizers.add_grid_l1_`` at the marked rows: ``weight * mean |v|`` of each of the six
    factors, averaged, its (sub)gradient added where a row is marked."""
    total = 0.0
    for table in grads.tables():
        total += _l1_loop(table.table.detach().numpy(), table.buffer().numpy(), table.marks,
                          table.part_starts.astype(np.int64), l1_coefficients(table, weight))
    return total


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
        total += _tv_plane_loop(table, grad, grads.plane.marks, int(plane_off[i]), h, w, scale_y, scale_x)
    table, grad = lines.detach().numpy(), grads.line.buffer().numpy()
    for i, (_, axis) in enumerate(MODES):
        n = int(res[axis])
        scale_y = scale / max(1, (n - 1) * c) if n > 1 else 0.0
        total += _tv_plane_loop(table, grad, grads.line.marks, int(line_off[i]), n, 1, scale_y, 0.0)
    return total
