"""A VM grid read by the fused training step: decoder rows forward, row-sparse factor gradients backward.

``GridRows.rows`` is differentiable in the parameter features ``q`` (autograd) and in the grid's
tables, whose gradient its backward leaves as pending taps in ``RowGradients``
(``table_gradients``): the optimizer updates only the rows they reach (``training.sparse_adam``).
The loops are ``vm_rows_kernel``'s; ``VMGrid.sample`` with ``field.modulate`` is the slow twin.
"""

from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor

from visnerf import compiled
from visnerf.representation.table_gradients import PendingTaps, RowGradients
from visnerf.representation.vm import VMGrid
from visnerf.representation.vm_kernel import table_layout
from visnerf.representation.vm_rows_kernel import loops
from visnerf.representation.vm_taps import MODES

FLOAT_TYPES = {torch.float32: np.float32, torch.float64: np.float64}


@dataclass
class Taps:
    """What a forward keeps for a backward: each sample's first plane row, four plane weights,
    first line row and two line weights per mode, and its plane values ``[3, m, c]``."""

    plane_rows: np.ndarray
    plane_weights: np.ndarray
    line_rows: np.ndarray
    line_weights: np.ndarray
    plane_values: np.ndarray

    @classmethod
    def empty(cls, m: int, c: int, float_type: type) -> "Taps":
        return cls(np.empty((m, 3), np.int64), np.empty((m, 3, 4), float_type), np.empty((m, 3), np.int64),
                   np.empty((m, 3, 2), float_type), np.empty((3, m, c), float_type))

    def __len__(self) -> int:
        return self.plane_rows.shape[0]

    def select(self, index: Tensor) -> "Taps":
        """The taps of samples ``index`` (int64), gathered by torch on every thread (numpy's fancy
        indexing runs on one)."""

        def take(a: np.ndarray, dim: int = 0) -> np.ndarray:
            return torch.from_numpy(a).index_select(dim, index).numpy()

        return Taps(take(self.plane_rows), take(self.plane_weights), take(self.line_rows), take(self.line_weights),
                    take(self.plane_values, 1))


def _forward(rows: "GridRows", q: Tensor, coords: Tensor, ray: Tensor, tail: Tensor, n_freqs: int,
             save: bool) -> tuple[Tensor, Taps]:
    """The rows of the samples (and, with ``save``, their taps), on one thread per part."""
    planes, lines = rows.grid.row_tables()
    m = coords.shape[0]
    out = torch.empty(m, rows.width(q.shape[1], n_freqs, tail.shape[1]), dtype=planes.dtype)
    forward, _ = rows.loops(q.shape[1])
    res, plane_off, line_off = rows.layout
    taps = Taps.empty(m if save else 1, rows.n_components, rows.float_type)
    arrays = (_np(coords), _np(ray), _np(q), _np(tail), planes.detach().numpy(), lines.detach().numpy(),
              res, plane_off, line_off, n_freqs, out.numpy(), bool(save), taps.plane_rows, taps.plane_weights,
              taps.line_rows, taps.line_weights, taps.plane_values)
    compiled.run_ranges(lambda a, b: forward(*arrays, a, b), m, MIN_SAMPLES_A_PART)
    return out, taps


def _backward(rows: "GridRows", q: Tensor, ray: Tensor, taps: Taps, grad_out: Tensor) -> Tensor:
    """Leave the tables' gradient as pending taps in ``rows.gradients``; returns ``q``'s."""
    grads = rows.gradients
    if grads is None or not grads.follows(rows.grid):
        raise RuntimeError("the fused lookups' gradients were not set up for this grid (GridRows.gradients)")
    if len(taps) != ray.shape[0]:
        raise RuntimeError("the fused lookups kept no taps for a backward (rows taken without gradients)")
    _, row_gradients = rows.loops(q.shape[1])
    planes, lines = rows.grid.row_tables()
    m, c = ray.shape[0], rows.n_components
    grad_plane_value = np.empty((3, m, c), rows.float_type)
    grad_line_value = np.empty((3, m, c), rows.float_type)
    arrays = (_np(ray), _np(q), _np(grad_out.to(planes.dtype)), lines.detach().numpy(), taps.line_rows,
              taps.line_weights, taps.plane_values, grad_plane_value, grad_line_value)

    def per_sample(a: int, b: int) -> Tensor:
        grad_q = torch.zeros_like(q)  # one per range: the ranges' sums are added in range order
        row_gradients(*arrays, grad_q.numpy(), a, b)
        return grad_q

    grad_q = compiled.run_ranges(per_sample, m, MIN_SAMPLES_A_PART)
    grads.plane.add(PendingTaps(taps.plane_rows, taps.plane_weights, rows.plane_corners, grad_plane_value))
    grads.line.add(PendingTaps(taps.line_rows, taps.line_weights, rows.line_corners, grad_line_value))
    return sum(grad_q[1:], grad_q[0])


class _Rows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, q, plane_table, line_table, rows: "GridRows", coords, ray, tail, n_freqs, save):
        out, taps = _forward(rows, q, coords, ray, tail, n_freqs, save)
        ctx.save_for_backward(q, ray)
        ctx.rows, ctx.taps = rows, taps
        return out

    @staticmethod
    def backward(ctx, grad_out):
        q, ray = ctx.saved_tensors
        return _backward(ctx.rows, q, ray, ctx.taps, grad_out), None, None, None, None, None, None, None, None


class _Selected(torch.autograd.Function):
    @staticmethod
    def forward(ctx, q, plane_table, line_table, taken: "TakenRows", index):
        ctx.save_for_backward(q, index)
        ctx.taken = taken
        return taken.rows.index_select(0, index)

    @staticmethod
    def backward(ctx, grad_out):
        q, index = ctx.saved_tensors
        taken: TakenRows = ctx.taken
        grad_q = _backward(taken.grid_rows, q, taken.ray.index_select(0, index), taken.taps.select(index), grad_out)
        return grad_q, None, None, None, None


@dataclass(frozen=True)
class TakenRows:
    """Rows taken once without a graph, with their taps, so that any subset of them can be made
    differentiable afterwards (``GridRows.select``) without reading the tables again."""

    grid_rows: "GridRows"
    rows: Tensor
    ray: Tensor
    taps: Taps


MIN_SAMPLES_A_PART = 2048
"""Fewest samples worth a thread of their own (smaller calls run on the caller's thread alone)."""


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
        res = self.layout[0]
        widths = [int(res[a]) for (a, _), _ in MODES]
        self.plane_corners = np.array([[0, 1, w, w + 1] for w in widths], np.int64)
        """Row offsets of a plane tap's four corners from its first row, per mode."""
        self.line_corners = np.array([[0, 1]] * 3, np.int64)
        self.n_components = grid.n_components
        self.float_type = FLOAT_TYPES[planes.dtype]

    def loops(self, n_q: int):  # two numba dispatchers (forward, row gradients)
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
        save = torch.is_grad_enabled() and (q.requires_grad or planes.requires_grad or lines.requires_grad)
        return _Rows.apply(q.to(dtype), planes, lines, self, coords.to(dtype), ray.to(torch.int64), tail.to(dtype),
                           int(n_freqs), save)

    @torch.no_grad()
    def take(
        self, coords: Float[Tensor, "m 3"], ray: Int[Tensor, " m"], q: Float[Tensor, "n c"], n_freqs: int = -1,
        tail: Float[Tensor, "n e"] | None = None,
    ) -> TakenRows:
        """``rows`` without a graph, kept with their taps for ``select``."""
        planes, _ = self.grid.row_tables()
        dtype = planes.dtype
        if tail is None:
            tail = torch.zeros(q.shape[0], 0, dtype=dtype)
        ray = ray.to(torch.int64)
        out, taps = _forward(self, q.detach().to(dtype), coords.to(dtype), ray, tail.to(dtype), int(n_freqs), True)
        return TakenRows(self, out, ray, taps)

    def select(self, taken: TakenRows, index: Int[Tensor, " k"], q: Float[Tensor, "n c"]) -> Float[Tensor, "k w"]:
        """Rows ``index`` of ``taken`` (made with these ``q`` values), differentiable in ``q`` and
        the tables as ``rows`` is."""
        planes, lines = self.grid.row_tables()
        return _Selected.apply(q.to(planes.dtype), planes, lines, taken, index.to(torch.int64))
