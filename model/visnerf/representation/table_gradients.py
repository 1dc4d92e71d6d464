"""The gradient of a VM table (a grid's stacked planes or lines) as the fused training step makes it.

A backward of the compiled lookups (``vm_rows``) does not write into the table's gradient: it
leaves ``PendingTaps``, the rows each sample's taps read with their weights and the gradient of
the value the taps made. The optimizer then sorts the taps by row (a counting pass,
``vm_rows_kernel.tap_index``) and updates each touched row from the sum of its taps' gradients
in one pass (``training.sparse_adam``): no table-sized gradient is written, read or zeroed (a
small table, a grid's lines, is summed sample by sample into a buffer instead, ``SCATTER_ROWS``).
Where a whole gradient is needed (gradients averaged over ranks, a prior that reads a row's
neighbours) ``materialize`` adds the taps into the table's ``.grad``, made once and kept, and
marks the rows it wrote; the optimizer then updates the marked rows and zeroes them.
"""

from dataclasses import dataclass, field
from typing import no_type_check

import numpy as np
import torch
from torch import Tensor, nn

from visnerf import compiled
from visnerf.representation.vm import VMGrid
from visnerf.representation.vm_kernel import table_layout
from visnerf.representation.vm_rows_kernel import gather_loop, tap_index

MIN_ROWS_A_PART = 4096
"""Fewest table rows worth a thread of their own when their taps are summed."""
SCATTER_ROWS = 4096
"""Tables of at most this many rows (the lines of a grid) take their taps sample by sample into a
row buffer instead of sorting them by row: every sample reads every line, so a few hundred rows
hold most of the taps, and a sorted gather reads the samples' gradients in random order for each
of them (docs/decisions.md#step.scatter_rows)."""


@no_type_check  # compiled by numba
def _scatter_taps(grad, marks, rows, weights, corners, values):
    """Add one backward's taps (``PendingTaps``) into ``grad`` sample by sample and mark their
    rows: each row's sum runs over its taps in sample order, as the sorted gather sums them."""
    c = grad.shape[1]
    for s in range(rows.shape[0]):
        for i in range(3):
            for k in range(corners.shape[1]):
                row = rows[s, i] + corners[i, k]
                w = weights[s, i, k]
                marks[row] = 1
                for ch in range(c):
                    grad[row, ch] += w * values[i, s, ch]


_scatter_loop = compiled.jit(_scatter_taps)


@dataclass(frozen=True)
class PendingTaps:
    """One backward's taps into a table: sample ``s`` reads, in mode ``i``, rows
    ``rows[s, i] + corners[i, k]`` with weights ``weights[s, i, k]``, and the gradient of the value
    it read there is ``values[i, s]`` (``[3, m, c]``)."""

    rows: np.ndarray
    weights: np.ndarray
    corners: np.ndarray
    values: np.ndarray


@dataclass(frozen=True)
class TapIndex:
    """Pending taps sorted by table row: row ``r``'s taps are ``taps[starts[r]:starts[r + 1]]``
    (flat indices into ``values`` ``[3 m, c]``), in sample order, with ``weights``."""

    starts: np.ndarray
    taps: np.ndarray
    weights: np.ndarray
    values: np.ndarray


@dataclass
class TableGradient:
    """The gradient of ``table`` in the making: pending taps, and a buffer with row marks."""

    table: nn.Parameter
    part_starts: np.ndarray
    """First row of each mode's plane (or line) in the table, and the row count at the end."""
    pending: list[PendingTaps] = field(default_factory=list)
    marks: np.ndarray = field(init=False)
    """1 where the buffer (``table.grad``) holds a gradient."""
    l1_coefficients: np.ndarray | None = None
    """Per mode, the coefficient of an L1 prior whose gradient the optimizer adds at each row it
    updates from pending taps (``training.row_priors``); None: no such prior."""
    l1_value: float = 0.0
    """The part of that prior at the rows the last update touched."""

    def __post_init__(self) -> None:
        self.marks = np.zeros(self.table.shape[0], np.uint8)
        self._counts: np.ndarray | None = None

    @property
    def n_rows(self) -> int:
        return self.table.shape[0]

    def follows(self, table: Tensor) -> bool:
        return table is self.table

    def add(self, taps: PendingTaps) -> None:
        self.pending.append(taps)

    def buffer(self) -> Tensor:
        """``table.grad``, made (zeros) where missing; kept from step to step."""
        if self.table.grad is None:
            self.table.grad = torch.zeros_like(self.table)
        return self.table.grad

    def index(self) -> TapIndex | None:
        """The pending taps sorted by row, and cleared (None where there are none)."""
        if not self.pending:
            return None
        parts, self.pending = self.pending, []
        corners = parts[0].corners
        if len(parts) == 1:
            rows, weights, values = parts[0].rows, parts[0].weights, parts[0].values
        else:  # several micro-batches: one index over all of them (samples in their order)
            rows = np.concatenate([p.rows for p in parts])
            weights = np.concatenate([p.weights for p in parts])
            values = np.concatenate([p.values for p in parts], axis=1)
        m, c = rows.shape[0], values.shape[2]
        starts = np.empty(self.n_rows + 1, np.int64)
        taps = np.empty(rows.size * corners.shape[1], np.int64)
        tap_weights = np.empty(taps.shape[0], values.dtype)
        tap_index(rows, weights, corners, self.n_rows, starts, taps, tap_weights, self._sort_counts())
        return TapIndex(starts, taps, tap_weights, values.reshape(3 * m, c))

    def scatter(self, grad: np.ndarray, marks: np.ndarray) -> None:
        """Add the pending taps into ``grad`` sample by sample, marking their rows in ``marks``,
        and clear them (for a small table, ``SCATTER_ROWS``)."""
        pending, self.pending = self.pending, []
        for taps in pending:
            _scatter_loop(grad, marks, taps.rows, taps.weights, taps.corners, taps.values)

    def _sort_counts(self) -> np.ndarray:
        """Scratch counts of ``tap_index``, one row per thread, made once per table."""
        threads = max(1, torch.get_num_threads())
        if self._counts is None or self._counts.shape[0] < threads:
            self._counts = np.zeros((threads, self.n_rows + 1), np.int64)
        return self._counts

    def materialize(self) -> None:
        """Add the pending taps into the buffer and mark the rows they reach: a small table's
        sample by sample (``scatter``), a large one's sorted by row and gathered on every thread."""
        if self.n_rows <= SCATTER_ROWS:
            self.scatter(self.buffer().numpy(), self.marks)
            return
        index = self.index()
        if index is None:
            return
        grad = self.buffer().numpy()
        loop = gather_loop(grad.shape[1], grad.dtype.type)
        compiled.run_ranges(lambda a, b: loop(grad, self.marks, index.starts, index.taps, index.weights,
                                              index.values, a, b), self.n_rows, MIN_ROWS_A_PART)

    def mark_all(self) -> None:
        """Count every row as holding a gradient (a rank's or a prior's reached all of them)."""
        self.marks[:] = 1


@dataclass
class RowGradients:
    """The gradients of one VM grid's two tables (``VMGrid.row_tables``)."""

    plane: TableGradient
    line: TableGradient

    @classmethod
    def of(cls, grid: VMGrid) -> "RowGradients":
        planes, lines = grid.row_tables()
        _, plane_off, line_off = table_layout(grid.resolution, planes.shape[0], lines.shape[0])
        return cls(TableGradient(planes, np.append(plane_off, planes.shape[0])),
                   TableGradient(lines, np.append(line_off, lines.shape[0])))

    def follows(self, grid: VMGrid) -> bool:
        """Whether these are still the gradients of ``grid``'s tables (resampling replaces them)."""
        planes, lines = grid.row_tables()
        return self.plane.follows(planes) and self.line.follows(lines)

    def tables(self) -> tuple[TableGradient, TableGradient]:
        return self.plane, self.line

    def materialize(self) -> None:
        for t in self.tables():
            t.materialize()
