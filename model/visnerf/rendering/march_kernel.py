"""The per-segment bookkeeping of ``renderer.march_rays`` as two compiled loops (CPU, numba).

A segment of the inference march places ``seg`` lattice samples on every active ray, keeps those
inside the ray's window and box and in an occupied cell, evaluates their densities, composites
them and picks the samples whose colour matters. The decoders and the lookups are one call each
(``FrameField``); the rest was about thirty torch operations over ``[a, seg]`` arrays a segment
(index grids, a mask, a nonzero, gathers, a cumulative sum, exponentials). Here:

- ``place``: the valid samples of a segment, compacted in ray-major order (the order of
  ``valid.view(-1).nonzero()``), with their flat index ``ray * seg + j``;
- ``accumulate``: the weighted colours of the samples picked added into their rays' sums (a
  ``cat``, a product and an ``index_add_`` as torch operations);
- ``composite``: their weights ``exp(-tau_before) * -expm1(-tau)`` (log-space transmittance,
  the exclusive running sum as ``volume.exclusive_optical_depth``), each ray's optical depth
  advanced, and the samples whose weight exceeds the threshold.

Both use the torch path's float32 arithmetic in the same order (a sample's position, its cell as
``EmptySpace.occupied_at``), so the frames agree to float rounding (tested); both release the GIL.
"""

import math
from typing import no_type_check

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor

from visnerf import compiled
from visnerf.rendering.empty_space_kernel import flat_cell


def available(device: torch.device) -> bool:
    """Whether the compiled loops serve ``device`` (``compiled.serves``)."""
    return compiled.serves(device)


@no_type_check  # compiled by numba
def _place(origins, directions, t_near, t_far, first, last, s0, seg, step64, use_occupancy, occupied, lower, cpu,
           last_cell, strides, out_points, out_flat):
    """Valid samples ``s0 .. s0 + seg - 1`` of each ray's window into ``out_points`` / ``out_flat``;
    returns their count."""
    step = np.float32(step64)
    half = np.float32(0.5)
    m = 0
    for r in range(origins.shape[0]):
        o0, o1, o2 = origins[r, 0], origins[r, 1], origins[r, 2]  # the ray's, read once
        d0, d1, d2 = directions[r, 0], directions[r, 1], directions[r, 2]
        near, far = t_near[r], t_far[r]
        base = first[r] + s0
        for j in range(min(seg, last[r] - base + 1)):
            t = near + step * (np.float32(base + j) + half)
            if not t < far:
                break
            p0 = o0 + d0 * t
            p1 = o1 + d1 * t
            p2 = o2 + d2 * t
            if use_occupancy:
                cells = ((p0 - lower[0]) * cpu[0], (p1 - lower[1]) * cpu[1], (p2 - lower[2]) * cpu[2])
                if occupied[flat_cell(cells, last_cell, strides)] == 0:
                    continue
            out_points[m, 0], out_points[m, 1], out_points[m, 2] = p0, p1, p2
            out_flat[m] = r * seg + j
            m += 1
    return m


@no_type_check
def _composite(flat, sigma, seg, step64, tau, threshold64, out_weights, out_shade):
    """Weights of samples ``flat`` (ray-major) with densities ``sigma``; adds each ray's optical
    depth to ``tau``; writes the indices of the samples heavier than ``threshold`` to
    ``out_shade`` and returns their count."""
    step = np.float32(step64)
    threshold = np.float32(threshold64)
    k = 0
    s = 0
    m = flat.shape[0]
    while s < m:
        r = flat[s] // seg
        before = tau[r]
        running = np.float32(0.0)  # optical depth of this segment's earlier samples
        while s < m and flat[s] // seg == r:
            depth = sigma[s] * step
            w = np.float32(math.exp(-(running + before))) * -np.float32(math.expm1(-depth))
            out_weights[s] = w
            if w > threshold:
                out_shade[k] = s
                k += 1
            running += depth
            s += 1
        tau[r] = before + running
    return k


@no_type_check
def _accumulate(rgbw, ray_idx, weights, shade, colors):
    """``rgbw[ray_idx[k]] += (weights[shade[k]] * colors[k], weights[shade[k]])`` for each ``k`` in
    order."""
    for k in range(shade.shape[0]):
        r = ray_idx[k]
        w = weights[shade[k]]
        rgbw[r, 0] += w * colors[k, 0]
        rgbw[r, 1] += w * colors[k, 1]
        rgbw[r, 2] += w * colors[k, 2]
        rgbw[r, 3] += w


_place_compiled, _composite_compiled = compiled.jit(_place), compiled.jit(_composite)
_accumulate_compiled = compiled.jit(_accumulate)


_NO_OCCUPANCY = (np.zeros(1, np.uint8), np.zeros(3, np.float32), np.zeros(3, np.float32), np.zeros(3, np.float32),
                 np.zeros(3, np.int64))


def place(
    origins: Float[Tensor, "a 3"],
    directions: Float[Tensor, "a 3"],
    t_near: Float[Tensor, " a"],
    t_far: Float[Tensor, " a"],
    first: Int[Tensor, " a"],
    last: Int[Tensor, " a"],
    s0: int,
    seg: int,
    step: float,
    occupancy: tuple[np.ndarray, ...] | None,
) -> tuple[Float[Tensor, "m 3"], Int[Tensor, " m"]]:
    """World positions and flat indices (``ray * seg + j``) of the valid samples of a segment;
    ``occupancy`` is ``GridTables(occupied, ...).arrays()`` of the ``EmptySpace`` marched, or None."""
    a = origins.shape[0]
    points = torch.empty(a * seg, 3, dtype=torch.float32)
    flat = torch.empty(a * seg, dtype=torch.int64)
    tables = _NO_OCCUPANCY if occupancy is None else occupancy
    arrays = [t.contiguous().numpy() for t in (origins, directions, t_near, t_far, first, last)]
    m = _place_compiled(*arrays, int(s0), int(seg), float(step), occupancy is not None, *tables, points.numpy(),
                        flat.numpy())
    return points[:m], flat[:m]


def composite(
    flat: Int[Tensor, " m"],
    sigma: Float[Tensor, " m"],
    seg: int,
    step: float,
    tau: Float[Tensor, " a"],
    threshold: float,
) -> tuple[Float[Tensor, " m"], Int[Tensor, " k"]]:
    """(weights of the samples, indices of those above ``threshold``); ``tau`` (contiguous) is
    advanced in place by each ray's optical depth in this segment."""
    m = flat.shape[0]
    weights = torch.empty(m, dtype=torch.float32)
    shade = torch.empty(m, dtype=torch.int64)
    k = _composite_compiled(flat.numpy(), sigma.contiguous().numpy(), int(seg), float(step), tau.numpy(),
                            float(threshold), weights.numpy(), shade.numpy())
    return weights, shade[:k]


def accumulate(
    rgbw: Float[Tensor, "n 4"],
    ray_idx: Int[Tensor, " k"],
    weights: Float[Tensor, " m"],
    shade: Int[Tensor, " s"],
    colors: Float[Tensor, "c 3"],
) -> None:
    """Add ``weights[shade] * colors`` and ``weights[shade]`` into rows ``ray_idx`` of ``rgbw``
    (columns r, g, b, weight; float32, contiguous), in place, in the order of the samples; the
    three index and colour arrays must have one row per sample (``k``)."""
    if rgbw.dtype != torch.float32 or not rgbw.is_contiguous() or colors.dtype != torch.float32:
        raise ValueError(f"rgbw and colors must be float32 and rgbw contiguous, got {rgbw.dtype} and {colors.dtype}")
    if not (ray_idx.shape[0] == shade.shape[0] == colors.shape[0]):
        raise ValueError(f"{ray_idx.shape[0]} rays, {shade.shape[0]} samples and {colors.shape[0]} colours differ")
    if shade.shape[0] > 0:
        _accumulate_compiled(rgbw.numpy(), ray_idx.contiguous().numpy(), weights.contiguous().numpy(),
                             shade.contiguous().numpy(), colors.contiguous().numpy())
