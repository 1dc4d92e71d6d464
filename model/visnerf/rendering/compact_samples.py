"""A training batch's samples, compact: only those evaluated, ray by ray (the fused step's layout).

``renderer.place_samples`` lays a batch out as ``[n_rays, longest window]`` with a mask, and every
later pass (occupancy, densities, weights, colours) walks the padded array or gathers from it.
Here one compiled loop places each ray's stratified samples ``t_near + step * (i + u)`` over its
window, keeps those in an occupied cell and writes them one after another: ray ``r`` owns samples
``offsets[r] .. offsets[r + 1] - 1``, front to back. The positions and the occupancy test are
``place_samples``' float arithmetic in the same order, so both keep the same samples (tested).
"""

import math
from dataclasses import dataclass
from typing import no_type_check

import numpy as np
import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from visnerf import compiled
from visnerf.rendering.aabb import intersect_aabb
from visnerf.rendering.sampling import uniform_noise


@dataclass(frozen=True)
class CompactSamples:
    """The samples of ``n`` rays a step evaluates, ray by ray."""

    points: Float[Tensor, "m 3"]
    ray: Int[Tensor, " m"]
    """The ray of each sample (non-decreasing)."""
    offsets: Int[Tensor, " n1"]
    """``n + 1`` starts: ray ``r``'s samples are ``offsets[r]`` to ``offsets[r + 1] - 1``."""
    sigma: Float[Tensor, " m"] | None = None
    """Densities of the samples computed without a graph (``drop_occluded``), where known."""

    @property
    def n_rays(self) -> int:
        return self.offsets.shape[0] - 1

    def __len__(self) -> int:
        return self.points.shape[0]

    def per_ray(self) -> Int[Tensor, " n"]:
        return self.offsets[1:] - self.offsets[:-1]

    def of_rays(self, rays: slice) -> "CompactSamples":
        """The samples of rays ``rays`` (a slice with a step of 1), their rays counted from 0."""
        start, stop, _ = rays.indices(self.n_rays)
        a, b = int(self.offsets[start]), int(self.offsets[stop])
        sigma = None if self.sigma is None else self.sigma[a:b]
        return CompactSamples(self.points[a:b], self.ray[a:b] - start, self.offsets[start:stop + 1] - a, sigma)

    def keep(self, kept: Bool[Tensor, " m"], sigma: Float[Tensor, " m"] | None = None) -> "CompactSamples":
        """The samples where ``kept`` holds (with ``sigma`` of every sample, if given, kept alike)."""
        index = kept.nonzero()[:, 0]
        counts = torch.bincount(self.ray.index_select(0, index), minlength=self.n_rays)
        offsets = torch.cat([counts.new_zeros(1), counts.cumsum(0)])
        return CompactSamples(self.points.index_select(0, index), self.ray.index_select(0, index), offsets,
                              None if sigma is None else sigma.index_select(0, index))


def _place_source(ft: type):  # the loop numba compiles for float type ``ft``
    @no_type_check  # compiled by numba
    def _place(origins, directions, t_near, t_far, start, stop, hit, jitter, step, use_occupancy, occupied, lower,
                extent, res, out_points, out_ray, offsets, first, last, m0):
        """Samples ``start[r] .. stop[r]`` of each ray ``first <= r < last`` before ``t_far`` (in an
        occupied cell with ``use_occupancy``) into ``out_points`` / ``out_ray`` from row ``m0`` on;
        ``offsets[r + 1]`` the row after ray ``r``'s. Returns the row after the last."""
        m = m0
        n0, n1, n2 = int(res[0]), int(res[1]), int(res[2])
        for r in range(first, last):
            if hit[r]:
                o0, o1, o2 = origins[r, 0], origins[r, 1], origins[r, 2]  # the ray's, read once
                d0, d1, d2 = directions[r, 0], directions[r, 1], directions[r, 2]
                near, far, u = t_near[r], t_far[r], jitter[r]
                for i in range(start[r], stop[r] + 1):
                    t = near + step * (ft(i) + u)
                    if not t < far:
                        break
                    p0 = o0 + d0 * t
                    p1 = o1 + d1 * t
                    p2 = o2 + d2 * t
                    if use_occupancy:
                        r0 = (p0 - lower[0]) / extent[0]
                        r1 = (p1 - lower[1]) / extent[1]
                        r2 = (p2 - lower[2]) / extent[2]
                        if not (r0 >= 0 and r0 <= 1 and r1 >= 0 and r1 <= 1 and r2 >= 0 and r2 <= 1):
                            continue
                        i0 = min(max(int(r0 * res[0]), 0), n0 - 1)
                        i1 = min(max(int(r1 * res[1]), 0), n1 - 1)
                        i2 = min(max(int(r2 * res[2]), 0), n2 - 1)
                        if occupied[(i0 * n1 + i1) * n2 + i2] == 0:
                            continue
                    out_points[m, 0] = p0
                    out_points[m, 1] = p1
                    out_points[m, 2] = p2
                    out_ray[m] = r
                    m += 1
            offsets[r + 1] = m
        return m

    return _place


MIN_RAYS_A_PART = 256
"""Fewest rays worth a thread of their own when a batch's samples are placed."""
_PLACE_LOOPS = {np.float32: compiled.jit(_place_source(np.float32)),
                np.float64: compiled.jit(_place_source(np.float64))}


def available(device: torch.device) -> bool:
    """Whether the compiled loop serves ``device`` (``compiled.serves``)."""
    return compiled.serves(device)


@torch.no_grad()
def place_compact(
    aabb: Float[Tensor, "2 3"],
    rays_o: Float[Tensor, "n 3"],
    rays_d: Float[Tensor, "n 3"],
    step: float,
    max_samples: int,
    occupancy: Bool[Tensor, "x y z"] | None,
    generator: torch.Generator | None = None,
    windows: tuple[Int[Tensor, " n"], Int[Tensor, " n"]] | None = None,
) -> CompactSamples:
    """``renderer.place_samples`` laid out compact: stratified with ``generator`` (one jitter per
    ray, drawn as there), within ``windows`` (first, last) where given, in ``occupancy``'s cells."""
    t_near, t_far, hit = intersect_aabb(rays_o, rays_d, aabb)
    span = float((t_far - t_near).max()) if hit.any() else 0.0
    n_samples = max(1, min(max_samples, math.ceil(span / step)))
    dtype = rays_o.dtype
    jitter = torch.full_like(t_near, 0.5)
    if generator is not None:
        jitter = uniform_noise((rays_o.shape[0],), generator, rays_o.device).to(dtype)
    if windows is None:
        start = torch.zeros_like(t_near, dtype=torch.int64)
        stop = torch.full_like(start, n_samples - 1)
    else:
        start, stop = windows[0].clamp_min(0), windows[1].clamp_max(n_samples - 1)
    n = rays_o.shape[0]
    room = torch.cat([start.new_zeros(1), (stop - start + 1).clamp_min(0).cumsum(0)])  # [n + 1] each ray's rows at most
    points = torch.empty(int(room[-1]), 3, dtype=dtype)
    ray = torch.empty(int(room[-1]), dtype=torch.int64)
    offsets = torch.zeros(n + 1, dtype=torch.int64)
    use = occupancy is not None
    grid = occupancy.reshape(-1).view(torch.uint8) if use else torch.zeros(1, dtype=torch.uint8)  # bool bytes, no copy
    res = torch.tensor(occupancy.shape if use else (1, 1, 1), dtype=dtype)
    extent = (aabb[1] - aabb[0]).clamp_min(torch.finfo(dtype).eps).to(dtype)
    ft = np.float32 if dtype == torch.float32 else np.float64
    arrays = [t.contiguous().numpy() for t in (rays_o, rays_d, t_near, t_far, start.to(torch.int64),
                                               stop.to(torch.int64), hit, jitter)]
    rest = (ft(step), use, grid.numpy(), aabb[0].to(dtype).numpy(), extent.numpy(), res.numpy(), points.numpy(),
            ray.numpy(), offsets.numpy())
    loop = _PLACE_LOOPS[ft]
    # ranges of rays on every thread, each writing from its rays' first possible row, then packed
    count = compiled.parts(n, MIN_RAYS_A_PART)
    cuts = [n * i // count for i in range(count + 1)]
    bases = [int(room[c]) for c in cuts[:-1]]  # each range's first row
    ends = [0] * count

    def part(i: int) -> None:
        ends[i] = loop(*arrays, *rest, cuts[i], cuts[i + 1], bases[i])

    compiled.run_parts(part, count)
    m = ends[0]
    for i in range(1, count):  # move each range's rows to follow the ones before (order kept)
        base, k = bases[i], ends[i] - bases[i]
        if base != m:
            points[m:m + k] = points[base:base + k].clone()
            ray[m:m + k] = ray[base:base + k].clone()
            offsets[cuts[i] + 1:cuts[i + 1] + 1] -= base - m
        m += k
    return CompactSamples(points[:m], ray[:m], offsets)
