"""One compiled pass per sample for the decoders' input rows (CPU inference, numba).

``FrameField`` fills a decoder's input row with the VM features of a sample (plane times line,
three modes) and, for density, its positional encoding. As torch operations that is about a dozen
passes over ``[m, k]`` arrays: the taps' rows and weights (``TapLayout.taps``), two
``embedding_bag`` sums, their product, a cast and the encoding's product and sine. Here one loop
over the samples computes the interpolation, reads the rows and writes the finished row, in less
than half the time (docs/decisions.md#frames.compiled_rows). The loop releases the GIL, so the chunk
threads of a frame run it side by side.

The tables are read in float32 (the model's own parameters, no per-frame copy) and a row is
rounded to bfloat16 once, when the decoders compute in bfloat16; the torch path rounds the table
and the interpolation weights first, so this pass is the closer of the two to the float32 field.

The interpolation is that of ``vm_taps`` (``align_corners=True``, the border read outside
[-1, 1], the lower node at most ``n - 2``), the encoding that of ``decoders.encode_position``;
``tests/model/representation/test_vm_kernel.py`` checks both against those references.
"""

import functools
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import no_type_check

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from visnerf import compiled
from visnerf.representation.vm_taps import MODES


def available(device: torch.device) -> bool:
    """Whether the compiled pass serves ``device`` (``compiled.serves``)."""
    return compiled.serves(device)


@functools.cache
def axis_loop(ft: type):  # an inlined numba helper
    """The lower node (unsigned) and fraction of grid coordinate ``x`` on an axis of ``n`` nodes,
    in ``ft`` (``vm_taps``' interpolation)."""

    @no_type_check  # compiled by numba: no runtime type checks (tests run jaxtyping's import hook)
    def _axis(x, n):
        one = ft(1.0)
        if not x >= -one:  # NaN reads the border too: no index outside the tables
            x = -one
        elif x > one:
            x = one
        half = ft(0.5) * ft(n - 1)
        pos = half * x + half
        lo = min(np.floor(pos), ft(n - 2))  # in ``ft``: no round trip through an integer
        return np.uint64(lo), pos - lo

    return compiled.jit(_axis, inline=True)


@functools.cache
def interpolation_loop(ft: type):  # an inlined numba helper
    """Each axis's lower node and fraction of sample ``s`` in ``ft`` (``axis_loop``)."""
    axis = axis_loop(ft)

    @no_type_check
    def _interpolation(coords, s, res, lower, frac):
        for a in range(3):
            lo, fr = axis(coords[s, a], res[a])
            lower[a] = lo
            frac[a] = fr

    return compiled.jit(_interpolation, inline=True)


@functools.cache
def encoding_loop(ft: type):  # an inlined numba helper
    """``encode_position``'s columns of sample ``s`` into ``out[r, col:]``: the coordinates, then
    ``6 n_freqs`` sines and cosines, level 0 from libm and each later level by the double-angle
    formulas (one rounding a level instead of a sine and a cosine call)."""

    @no_type_check
    def _encode(coords, s, n_freqs, out, r, col):
        for a in range(3):
            out[r, col + a] = coords[s, a]
        for a in range(3):
            angle = coords[s, a] * ft(math.pi)
            sn, cs = ft(math.sin(angle)), ft(math.cos(angle))
            for level in range(n_freqs):
                out[r, col + 3 + 6 * level + a] = sn
                out[r, col + 6 + 6 * level + a] = cs
                sn, cs = ft(2.0) * sn * cs, (cs - sn) * (cs + sn)

    return compiled.jit(_encode, inline=True)


@no_type_check
def _store_row(row, row_bits, s, width, to_bf16, out, out_bits):
    """Row ``s`` of the output from the scratch row: copied (float32) or rounded to the nearest
    even bfloat16 (its bits; NaN stays NaN, where rounding could carry it to 0); unsigned indices
    as ``mode_loop``'s."""
    su = np.uint64(s)
    if to_bf16:
        for j in range(width):
            ju = np.uint64(j)
            b = row_bits[ju]
            rounded = np.uint16((b + np.uint32(0x7FFF) + ((b >> np.uint32(16)) & np.uint32(1))) >> np.uint32(16))
            out_bits[su, ju] = np.uint16(0x7FC0) if (b & np.uint32(0x7FFFFFFF)) > np.uint32(0x7F800000) else rounded
    else:
        for j in range(width):
            ju = np.uint64(j)
            out[su, ju] = row[ju]


store_row = compiled.jit(_store_row, inline=True)


@functools.cache
def mode_loop(c: int, ft: type):  # an inlined numba helper
    """One mode's ``c`` features of a sample into ``row[col:col + c]``: the bilinear plane value
    at flat row ``r00`` (``w`` rows to the next line of the plane) times the linear line value at
    flat row ``l0``, ``plane`` and ``line`` flattened. Every index is unsigned: numba wraps a
    signed index that may be negative, a branch per read that keeps LLVM from vectorising the
    channel loop (docs/decisions.md#frames.compiled_rows)."""

    @no_type_check
    def _mode(plane, line, r00, w, l0, fa, fb, fl, row, col):
        one = ft(1.0)
        cu = np.uint64(c)
        w00, w10 = (one - fa) * (one - fb), fa * (one - fb)
        w01, w11 = (one - fa) * fb, fa * fb
        fl0 = one - fl
        a = r00 * cu
        b = (r00 + w) * cu
        q = l0 * cu
        for ch in range(c):
            k = np.uint64(ch)
            p = (w00 * plane[a + k] + w10 * plane[a + cu + k]) + (w01 * plane[b + k] + w11 * plane[b + cu + k])
            row[col + k] = p * (fl0 * line[q + k] + fl * line[q + cu + k])

    return compiled.jit(_mode, inline=True)


def _kernel_source(c: int):  # the loop numba compiles for ``c`` channels
    """The loop for tables of ``c`` channels, compiled once per channel count (``_compiled``): a
    mode's channel loop of known length over flattened tables with unsigned indices (``mode_loop``)
    and no view made per sample, which numba counts references to; docs/decisions.md#frames.compiled_rows."""
    axis = axis_loop(np.float32)
    encode = encoding_loop(np.float32)
    mode = mode_loop(c, np.float32)

    @no_type_check
    def _kernel(coords, plane, line, res, plane_off, line_off, n_freqs, out, out_bits, to_bf16):
        """Rows ``out[s]`` (float32) or ``out_bits[s]`` (bfloat16 bits, round to nearest even) of the
        samples ``coords[s]``: ``3c`` VM features, then, where ``n_freqs >= 0``, the coordinates and
        their ``6 n_freqs`` sines and cosines (``encode_position``'s column order)."""
        nf = 3 * c
        width = nf if n_freqs < 0 else nf + 3 + 6 * n_freqs
        row = np.empty((1, width), np.float32)  # scratch, written, then copied or rounded into the output
        flat_row = row.reshape(-1)
        row_bits = flat_row.view(np.uint32)
        flat_plane = plane.reshape(-1)
        flat_line = line.reshape(-1)
        nx, ny, nz = res[0], res[1], res[2]
        ux, uy = np.uint64(nx), np.uint64(ny)
        p0, p1, p2 = np.uint64(plane_off[0]), np.uint64(plane_off[1]), np.uint64(plane_off[2])
        l0, l1, l2 = np.uint64(line_off[0]), np.uint64(line_off[1]), np.uint64(line_off[2])
        for s in range(coords.shape[0]):
            x0, fx = axis(coords[s, 0], nx)
            y0, fy = axis(coords[s, 1], ny)
            z0, fz = axis(coords[s, 2], nz)
            # the modes of ``MODES`` (``_MODES_WRITTEN_OUT``): planes xy, xz, yz with lines z, y, x
            mode(flat_plane, flat_line, p0 + y0 * ux + x0, ux, l0 + z0, fx, fy, fz, flat_row, np.uint64(0))
            mode(flat_plane, flat_line, p1 + z0 * ux + x0, ux, l1 + y0, fx, fz, fy, flat_row, np.uint64(c))
            mode(flat_plane, flat_line, p2 + z0 * uy + y0, uy, l2 + x0, fy, fz, fx, flat_row, np.uint64(2 * c))
            if n_freqs >= 0:
                encode(coords, s, n_freqs, row, 0, nf)
            store_row(flat_row, row_bits, s, width, to_bf16, out, out_bits)

    return _kernel


_MODES_WRITTEN_OUT = (((0, 1), 2), ((0, 2), 1), ((1, 2), 0))
if MODES != _MODES_WRITTEN_OUT:  # pragma: no cover - the pass writes the modes out, as these
    raise ImportError(f"vm_kernel's pass writes out the modes {_MODES_WRITTEN_OUT}, vm_taps has {MODES}")


@no_type_check
def _plane_axes(i):
    """(plane width axis, plane height axis, line axis) of mode ``i`` (``vm_taps.MODES``)."""
    if i == 0:
        return MODES[0][0][0], MODES[0][0][1], MODES[0][1]
    if i == 1:
        return MODES[1][0][0], MODES[1][0][1], MODES[1][1]
    return MODES[2][0][0], MODES[2][0][1], MODES[2][1]


plane_axes = compiled.jit(_plane_axes, inline=True)


@functools.cache
def _compiled(n_components: int):  # a numba dispatcher
    """The pass for tables of ``n_components`` channels, compiled once per count and process
    (numba's disk cache keeps one entry per count)."""
    return compiled.jit(_kernel_source(n_components))


def table_layout(
    resolution: tuple[int, int, int], plane_rows: int, line_rows: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(resolution, first plane row of each mode, first line row of each mode) as the compiled
    loops read them (int64); ``ValueError`` where tables of ``plane_rows`` and ``line_rows`` rows
    do not hold a grid of ``resolution``."""
    plane_off, line_off, p0, l0 = [], [], 0, 0
    for (a, b), c in MODES:
        plane_off.append(p0)
        line_off.append(l0)
        p0 += resolution[a] * resolution[b]
        l0 += resolution[c]
    if (p0, l0) != (plane_rows, line_rows):
        raise ValueError(f"tables of {plane_rows} plane and {line_rows} line rows do not "
                         f"match resolution {resolution} ({p0} and {l0})")
    return np.asarray(resolution, np.int64), np.asarray(plane_off, np.int64), np.asarray(line_off, np.int64)


@dataclass(frozen=True)
class KernelTables:
    """A VM grid's row tables (float32, the layout of ``vm_taps.TapLayout``) and where each mode's
    plane and line start in them, as the compiled pass reads them."""

    plane: np.ndarray
    """``[sum h * w, c]`` float32."""
    line: np.ndarray
    """``[sum r, c]`` float32."""
    resolution: np.ndarray
    plane_offsets: np.ndarray
    line_offsets: np.ndarray
    n_components: int
    _keep: tuple[Tensor, Tensor]
    """The tensors whose memory ``plane`` and ``line`` share."""

    @classmethod
    def of(cls, plane_table: Float[Tensor, "p c"], line_table: Float[Tensor, "l c"],
           resolution: tuple[int, int, int]) -> "KernelTables":
        plane_t, line_t = (t.detach().to(torch.float32).contiguous() for t in (plane_table, line_table))
        res, plane_off, line_off = table_layout(resolution, plane_t.shape[0], line_t.shape[0])
        return cls(plane_t.numpy(), line_t.numpy(), res, plane_off, line_off, int(plane_t.shape[1]), (plane_t, line_t))

    def write_rows(self, coords: Float[Tensor, "m 3"], out: Tensor, n_freqs: int = -1) -> None:
        """Write the features of grid coordinates ``coords`` (float32, CPU) into ``out[:, :3c]``
        and, for ``n_freqs >= 0``, their positional encoding into the next ``3 + 6 n_freqs``
        columns. ``out`` is float32 or bfloat16 with unit column stride (a row slice of a
        decoder's input)."""
        if compiled.numba is None:  # pragma: no cover
            raise RuntimeError("numba is not installed: the compiled VM lookup is unavailable")
        m = coords.shape[0]
        width = 3 * self.n_components + (0 if n_freqs < 0 else 3 + 6 * n_freqs)
        if out.shape[0] != m or out.shape[1] < width or out.stride(1) != 1 or coords.dtype != torch.float32:
            raise ValueError(f"out {tuple(out.shape)} (stride {out.stride()}) cannot take {m} rows of {width} "
                             f"columns from {coords.dtype} coordinates")
        if m == 0:
            return
        pts = coords.detach().contiguous().numpy()
        kernel = _compiled(self.n_components)
        if out.dtype == torch.bfloat16:
            bits = out.view(torch.int16).numpy().view(np.uint16)
            kernel(pts, self.plane, self.line, self.resolution, self.plane_offsets, self.line_offsets,
                   n_freqs, _NO_FLOATS, bits, True)
        elif out.dtype == torch.float32:
            kernel(pts, self.plane, self.line, self.resolution, self.plane_offsets, self.line_offsets,
                   n_freqs, out.numpy(), _NO_BITS, False)
        else:
            raise ValueError(f"out must be float32 or bfloat16, got {out.dtype}")


_NO_FLOATS = np.empty((1, 1), np.float32)
_NO_BITS = np.empty((1, 1), np.uint16)


def warm_up(channel_counts: Iterable[int] = (1,)) -> None:
    """Compile (or load from numba's cache) both variants of the pass, float32 and bfloat16 rows,
    for tables of each of ``channel_counts`` channels (a scene's density and appearance component
    counts), so that a server's first frame does not pay for it (about a second each when nothing
    is cached)."""
    if compiled.numba is None:  # pragma: no cover
        return
    coords = torch.zeros(1, 3)
    for c in sorted(set(channel_counts)):
        tables = KernelTables.of(torch.zeros(3 * 4, c), torch.zeros(3 * 2, c), (2, 2, 2))
        for dtype in (torch.float32, torch.bfloat16):
            tables.write_rows(coords, torch.empty(1, 3 * c + 3 + 6, dtype=dtype), 1)
