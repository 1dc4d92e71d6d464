"""A VM grid read by the fused training step: decoder rows forward, row-sparse factor gradients backward.

``GridRows.rows`` is differentiable in the parameter features ``q`` (autograd) and in the grid's
tables, whose gradient its backward adds straight into ``RowGradients``: the tables' ``.grad``,
kept from step to step, and one mark per table row that holds a gradient, so that the optimizer
updates (and clears) only the rows a step touched (``training.sparse_adam``). The loops are
``vm_rows_kernel``'s; ``VMGrid.sample`` with ``field.modulate`` is the slow twin.
"""

from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor

from visnerf.representation.vm import VMGrid
from visnerf.representation.vm_kernel import table_layout
from visnerf.representation.vm_rows_kernel import loops

FLOAT_TYPES = {torch.float32: np.float32, torch.float64: np.float64}


@dataclass
class RowGradients:
    """Gradients of one VM grid's tables as the fused step accumulates them.

    ``plane`` and ``line`` are the tables' ``.grad`` (made once, zeroed row by row by the
    optimizer after each step); ``plane_marks[i]`` is 1 where row ``i`` holds a gradient."""

    plane: Tensor
    line: Tensor
    plane_marks: np.ndarray
    line_marks: np.ndarray

    @classmethod
    def of(cls, grid: VMGrid) -> "RowGradients":
        """Zero gradients over ``grid``'s tables, installed as their ``.grad``."""
        planes, lines = grid.row_tables()
        for table in (planes, lines):
            table.grad = torch.zeros_like(table)
        return cls(planes.grad, lines.grad, np.zeros(planes.shape[0], np.uint8),
                   np.zeros(lines.shape[0], np.uint8))

    def follows(self, grid: VMGrid) -> bool:
        """Whether these are still the gradients of ``grid``'s tables (resampling replaces them)."""
        planes, lines = grid.row_tables()
        return planes.grad is self.plane and lines.grad is self.line

    def mark_all(self) -> None:
        """Count every row as touched (a prior or a rank's gradient reached all of them)."""
        self.plane_marks[:] = 1
        self.line_marks[:] = 1


class _Rows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, q, plane_table, line_table, rows: "GridRows", coords, ray, tail, n_freqs):  # noqa: ANN001, ANN205
        width = rows.width(q.shape[1], n_freqs, tail.shape[1])
        out = torch.empty(coords.shape[0], width, dtype=plane_table.dtype)
        forward, _ = rows.loops(q.shape[1])
        res, plane_off, line_off = rows.layout
        if coords.shape[0]:
            forward(_np(coords), _np(ray), _np(q), _np(tail), plane_table.detach().numpy(),
                    line_table.detach().numpy(), res, plane_off, line_off, n_freqs, out.numpy())
        ctx.save_for_backward(q, coords, ray)
        ctx.rows = rows
        return out

    @staticmethod
    def backward(ctx, grad_out):  # noqa: ANN001, ANN205
        q, coords, ray = ctx.saved_tensors
        rows: GridRows = ctx.rows
        grads = rows.gradients
        if grads is None or not grads.follows(rows.grid):
            raise RuntimeError("the fused lookups' gradients were not set up for this grid (GridRows.gradients)")
        grad_q = torch.zeros_like(q)
        _, backward = rows.loops(q.shape[1])
        res, plane_off, line_off = rows.layout
        planes, lines = rows.grid.row_tables()
        if coords.shape[0]:
            backward(_np(coords), _np(ray), _np(q), _np(grad_out.to(planes.dtype)), planes.detach().numpy(),
                     lines.detach().numpy(), res, plane_off, line_off, grads.plane.numpy(), grads.line.numpy(),
                     grad_q.numpy(), grads.plane_marks, grads.line_marks)
        return grad_q, None, None, None, None, None, None, None


def _np(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class GridRows:
    """Decoder rows of one VM grid at training samples (CPU): ``[F * q_rep, q, encoding or tail]``
    (``vm_rows_kernel``), differentiable in ``q`` and, through ``gradients``, in the tables."""

    def __init__(self, grid: VMGrid, gradients: RowGradients | None = None) -> None:
        planes, lines = grid.row_tables()
        if planes.dtype not in FLOAT_TYPES or planes.device.type != "cpu":
            raise ValueError(f"the fused lookups read float32 or float64 tables on the CPU, not {planes.dtype} "
                             f"on {planes.device}")
        self.grid = grid
        self.gradients = gradients
        self.layout = table_layout(grid.resolution, planes.shape[0], lines.shape[0])
        self.n_components = grid.n_components
        self.float_type = FLOAT_TYPES[planes.dtype]

    def loops(self, n_q: int):  # noqa: ANN201 - two numba dispatchers
        return loops(self.n_components, n_q, self.float_type)

    def width(self, n_q: int, n_freqs: int, n_tail: int) -> int:
        """Columns of a row: ``3c`` features, ``n_q`` parameter features, the encoding, the tail."""
        return 3 * self.n_components + n_q + (3 + 6 * n_freqs if n_freqs >= 0 else 0) + n_tail

    def rows(
        self,
        coords: Float[Tensor, "m 3"],
        ray: Int[Tensor, " m"],
        q: Float[Tensor, "n c"],
        n_freqs: int = -1,
        tail: Float[Tensor, "n e"] | None = None,
    ) -> Float[Tensor, "m w"]:
        """Rows of samples at grid coordinates ``coords`` whose rays are ``ray`` (indices into
        ``q`` and ``tail``): the modulated features, ``q``, then the positional encoding of
        ``n_freqs`` frequencies (none for -1) and the ray's ``tail`` columns."""
        planes, lines = self.grid.row_tables()
        dtype = planes.dtype
        if tail is None:
            tail = torch.zeros(q.shape[0], 0, dtype=dtype)
        return _Rows.apply(q.to(dtype), planes, lines, self, coords.to(dtype), ray.to(torch.int64), tail.to(dtype),
                           int(n_freqs))
