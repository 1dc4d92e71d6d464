"""Where a VM grid is read: the rows and weights of each sample's bilinear (planes) and linear
(lines) interpolation, for ``embedding_bag`` lookups on row tables (training and inference).

Grid coordinates are in [-1, 1] with ``align_corners=True`` (as ``vm.py``); outside reads the
border. A plane of mode ``i`` (axes ``(a, b)``) is stored ``[c, n_b, n_a]``; as a row table its row
``y * n_a + x`` holds node ``(x, y)``.
"""

import warnings
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from jaxtyping import Float, Int
from torch import Tensor

MODES: tuple[tuple[tuple[int, int], int], ...] = (((0, 1), 2), ((0, 2), 1), ((1, 2), 0))
"""(plane axes, line axis) of each mode, as indices into (x, y, z)."""


def take_rows(t: Tensor, index: Int[Tensor, " k"] | slice) -> Tensor:
    return t[index] if isinstance(index, slice) else t.index_select(0, index)


@dataclass(frozen=True)
class VMTaps:
    """Where a VM grid is read for ``m`` samples: for each of the three modes, the four plane rows
    and two line rows of its bilinear and linear interpolation, and their weights.

    The taps depend only on the grid's resolution, so the density and the appearance grid (same
    resolution) share them: colour reuses the taps its samples had for density.
    """

    plane_rows: Int[Tensor, "m 3 4"]
    plane_weights: Float[Tensor, "m 3 4"]
    line_rows: Int[Tensor, "m 3 2"]
    line_weights: Float[Tensor, "m 3 2"]

    def __len__(self) -> int:
        return self.plane_rows.shape[0]

    def select(self, index: Int[Tensor, " k"] | slice) -> "VMTaps":
        """Taps of samples ``index`` (a slice, or indices: ``index_select``, several times faster
        on the CPU than advanced indexing)."""
        tables = (self.plane_rows, self.plane_weights, self.line_rows, self.line_weights)
        return VMTaps(*(take_rows(t, index) for t in tables))


@dataclass(frozen=True)
class TapLayout:
    """Where the taps of a grid of one resolution point into the stacked tables.

    Interpolation along an axis is the same in every mode that uses the axis (same node count),
    so the lower node and the fraction are computed once per axis. Everything after that is linear
    in them, or a product of two such things, and is written as small matrix products, which
    write contiguous rows (broadcasting over the trailing 3 x 4 taps was five times slower):

    - rows: ``lower @ row_matrix + row_offset`` (each plane row is ``offset + y0 * w + x0`` plus
      its corner's 0, 1, w or w + 1; each line row ``offset + z0`` plus 0 or 1);
    - weights: ``(1 - f, f)`` of each axis picked by 0/1 matrices (exact), the plane weight being
      the product of the picks of its two axes.
    """

    resolution: tuple[int, int, int]
    half_span: Float[Tensor, " 3"]
    """(n - 1) / 2 per axis: grid coordinate [-1, 1] to node position [0, n - 1]."""
    last_lower: Float[Tensor, " 3"]
    """n - 2 per axis: the highest lower node."""
    row_matrix: Float[Tensor, "3 18"]
    row_offset: Float[Tensor, " 18"]
    """Rows from the lower nodes: twelve plane taps (three modes of four corners), then six line
    taps (three modes of two nodes)."""
    weight_picks: Float[Tensor, "6 30"]
    """Pick from ``(1 - f, f)`` of the three axes: the weight along each plane tap's width axis
    (12), along its height axis (12), and each line tap's (6)."""

    @classmethod
    def of(cls, resolution: tuple[int, int, int], device: torch.device) -> "TapLayout":
        if min(resolution) < 2:
            raise ValueError(f"VM grid of resolution {resolution} has an axis with fewer than 2 nodes")
        plane_m, plane_o = torch.zeros(3, 12), torch.zeros(12)
        line_m, line_o = torch.zeros(3, 6), torch.zeros(6)
        pick_u, pick_v, pick_l = torch.zeros(6, 12), torch.zeros(6, 12), torch.zeros(6, 6)
        plane_start = line_start = 0
        # ``both`` holds (1 - f) of the three axes, then f of the three axes.
        for i, ((a, b), c) in enumerate(MODES):
            w, h, n = resolution[a], resolution[b], resolution[c]
            for k, (dx, dy) in enumerate(((0, 0), (1, 0), (0, 1), (1, 1))):
                col = 4 * i + k
                plane_m[a, col], plane_m[b, col] = 1.0, float(w)
                plane_o[col] = plane_start + dx + dy * w
                pick_u[a + 3 * dx, col] = 1.0
                pick_v[b + 3 * dy, col] = 1.0
            for k in (0, 1):
                col = 2 * i + k
                line_m[c, col] = 1.0
                line_o[col] = line_start + k
                pick_l[c + 3 * k, col] = 1.0
            plane_start += w * h
            line_start += n
        res = torch.tensor(resolution, dtype=torch.float32)
        return cls(
            resolution=resolution,
            half_span=(0.5 * (res - 1.0)).to(device),
            last_lower=(res - 2.0).to(device),
            row_matrix=torch.cat([plane_m, line_m], dim=1).to(device),
            row_offset=torch.cat([plane_o, line_o]).to(device),
            weight_picks=torch.cat([pick_u, pick_v, pick_l], dim=1).to(device),
        )

    def taps(self, coords: Float[Tensor, "m 3"], dtype: torch.dtype) -> VMTaps:
        """Taps of grid coordinates in [-1, 1] (outside reads the border), computed in the
        coordinates' dtype; weights in ``dtype``. Row indices are exact in float32 below 2^24 rows."""
        m, ct = coords.shape[0], coords.dtype
        half_span = self.half_span.to(ct)
        pos = torch.addcmul(half_span, coords.clamp(-1.0, 1.0), half_span)  # [m, 3], in [0, n - 1]
        lower = torch.minimum(pos.floor(), self.last_lower.to(ct))
        frac = pos - lower
        both = torch.cat([1.0 - frac, frac], dim=1)  # [m, 6]
        rows = torch.addmm(self.row_offset.to(ct), lower, self.row_matrix.to(ct))  # [m, 18]
        picks = both @ self.weight_picks.to(ct)  # [m, 30]
        plane_rows = rows[:, :12].to(torch.int32).contiguous().view(m, 3, 4)
        line_rows = rows[:, 12:].to(torch.int32).contiguous().view(m, 3, 2)
        plane_weights = torch.mul(picks[:, :12], picks[:, 12:24]).to(dtype).view(m, 3, 4)
        line_weights = picks[:, 24:].to(dtype).contiguous().view(m, 3, 2)
        return VMTaps(plane_rows, plane_weights, line_rows, line_weights)


def grad_buffer(table: Tensor) -> Tensor:
    """``table.grad`` to accumulate into in place, created as zeros where None (a trainer's
    ``zero_grad`` sets it to None each step)."""
    if table.grad is None:
        table.grad = torch.zeros_like(table)
    return table.grad


def transposed_taps(rows: Int[Tensor, "m k"], weights: Float[Tensor, "m k"], n_rows: int) -> Tensor:
    """The transposed tap matrix ``T^T`` ``[n_rows, m]`` in compressed-row form: row ``r`` lists the
    samples that read table row ``r`` (in sample order: a stable sort, so products with it are
    deterministic) and their weights. Indices are int32 where they fit (faster products)."""
    m, k = rows.shape
    flat = rows.reshape(-1)
    index_dtype = torch.int32 if m * k < 2**31 else torch.int64
    order = torch.sort(flat, stable=True).indices  # [m * k]: taps grouped by table row
    crow = torch.zeros(n_rows + 1, dtype=index_dtype, device=rows.device)
    crow[1:] = torch.bincount(flat, minlength=n_rows).cumsum(0)
    col = torch.div(order, k, rounding_mode="floor").to(index_dtype)
    with warnings.catch_warnings():  # "sparse CSR support is in beta"
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(crow, col, weights.reshape(-1)[order], size=(n_rows, m), check_invariants=False)


class _WeightedRowSum(torch.autograd.Function):
    """``embedding_bag`` sum of weighted rows ``out[i] = sum_k w[i, k] * table[rows[i, k]]``,
    differentiable in the table, whose backward on the CPU is one sparse-dense product.

    The table's gradient is ``T^T @ grad`` for the tap matrix ``T [m, n_rows]``; ``T^T`` is built
    in compressed-row form from a stable sort of the taps (``transposed_taps``).
    ``embedding_bag``'s own CPU backward sorts the taps and adds one row per tap, and hands
    autograd a table-sized gradient to add (docs/decisions.md#step.torch_table_gradient). The product is
    deterministic and independent of the thread count (tested)."""

    @staticmethod
    def forward(ctx, table: Tensor, rows: Tensor, weights: Tensor) -> Tensor:
        ctx.save_for_backward(rows, weights)
        ctx.table_shape, ctx.table_dtype = table.shape, table.dtype
        return F.embedding_bag(rows, table, per_sample_weights=weights, mode="sum")

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, None, None]:
        rows, weights = ctx.saved_tensors
        taps_t = transposed_taps(rows, weights.to(ctx.table_dtype), ctx.table_shape[0])
        grad = grad.to(ctx.table_dtype).contiguous()
        return taps_t @ grad, None, None


def weighted_row_sum(
    rows: Int[Tensor, "m k"], weights: Float[Tensor, "m k"], table: Float[Tensor, "r c"]
) -> Float[Tensor, "m c"]:
    """``out[i] = sum_k weights[i, k] * table[rows[i, k]]``, differentiable in ``table`` (not in
    the weights). On the CPU its backward is a sparse-dense product (``_WeightedRowSum``); on other
    devices it is ``embedding_bag``'s own."""
    if table.requires_grad and table.device.type == "cpu" and torch.is_grad_enabled():
        return _WeightedRowSum.apply(table, rows, weights)
    return F.embedding_bag(rows, table, per_sample_weights=weights, mode="sum")


def lookup_modes(
    taps: VMTaps, plane_table: Float[Tensor, "p c"], line_table: Float[Tensor, "l c"]
) -> tuple[Float[Tensor, "n c"], Float[Tensor, "n c"]]:
    """Plane and line features of the three modes at the taps' samples, ``[3m, c]`` each (row
    ``3 * i + mode``): one weighted sum of rows per table (``weighted_row_sum``), differentiable in
    the tables. Their product, viewed ``[m, 3c]``, is the VM feature (``VMGrid.sample``)."""
    plane = weighted_row_sum(taps.plane_rows.view(-1, 4), taps.plane_weights.view(-1, 4), plane_table)
    line = weighted_row_sum(taps.line_rows.view(-1, 2), taps.line_weights.view(-1, 2), line_table)
    return plane, line
