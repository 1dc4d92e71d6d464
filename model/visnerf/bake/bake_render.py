"""Frames drawn from a bake on the CPU: the reference the browser's renderer is held to
(client/js/bake_renderer.js marches the same samples with the same arithmetic).

Samples lie ``step`` apart from where a ray enters the box, the first half a step in; a sample in
an unoccupied cell has no density. The raw density and the colour coefficients are interpolated
trilinearly between vertices; the density is ``softplus(raw) * scale``, the colour the
sigmoid of the coefficients' sum over the basis at the ray's direction (for ``level`` shading at
the normal of the raw density's four probes). Front to back, transmittance in log space.
"""

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor

from visnerf.bake.bake_file import Bake
from visnerf.bake.baking import colour_basis
from visnerf.data.cameras import Intrinsics, image_rays
from visnerf.rendering.aabb import intersect_aabb_torch
from visnerf.rendering.volume import composite_background, weights_from_optical_depth
from visnerf.representation.field import N_PROBES, probe_points

RAYS_A_PASS = 2048
SHADE_WEIGHT = 1e-6
"""Samples of at most this compositing weight are not shaded (their colour cannot reach 8 bits)."""


@dataclass(frozen=True)
class DenseBake:
    """A bake's arrays over the whole grid, as a renderer samples them."""

    bake: Bake
    raw: Float[Tensor, "1 1 z y x"]
    coefficients: Float[Tensor, "1 c z y x"]
    occupancy: Tensor
    """bool [z - 1, y - 1, x - 1]."""

    @classmethod
    def of(cls, bake: Bake) -> "DenseBake":
        raw = torch.from_numpy(bake.dense_raw())[None, None]
        coefficients = torch.from_numpy(bake.dense_coefficients()).permute(3, 0, 1, 2)[None].contiguous()
        return cls(bake, raw, coefficients, torch.from_numpy(bake.dense_occupancy()))

    def to_unit(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, "n 3"]:
        """World points to ``grid_sample`` coordinates (-1 and 1 at the first and last vertex)."""
        lo, hi = (torch.tensor(c, dtype=points.dtype) for c in self.bake.header.aabb)
        return (points - lo) / (hi - lo) * 2.0 - 1.0

    def sample(self, volume: Tensor, unit: Float[Tensor, "n 3"]) -> Float[Tensor, "n c"]:
        grid = unit.view(1, -1, 1, 1, 3)
        return F.grid_sample(volume, grid, mode="bilinear", padding_mode="border", align_corners=True)[0, :, :, 0, 0].T

    def occupied(self, unit: Float[Tensor, "n 3"]) -> Tensor:
        cells = torch.tensor(self.bake.header.cells, dtype=unit.dtype)  # x, y, z
        index = ((unit + 1.0) * 0.5 * cells).floor().long()
        index = torch.minimum(index.clamp_min(0), (cells - 1).long())
        return self.occupancy[index[:, 2], index[:, 1], index[:, 0]]


def render_bake(dense: DenseBake, c2w: Float[Tensor, "4 4"], intrinsics: Intrinsics) -> np.ndarray:
    """uint8 [height, width, 3], the bake drawn at camera ``c2w``."""
    rays_o, rays_d = image_rays(c2w.float(), intrinsics)
    o, d = rays_o.reshape(-1, 3), rays_d.reshape(-1, 3)
    out = torch.empty(o.shape[0], 3)
    for start in range(0, o.shape[0], RAYS_A_PASS):
        sl = slice(start, start + RAYS_A_PASS)
        out[sl] = _render_rays(dense, o[sl], d[sl])
    rgb = out.view(intrinsics.height, intrinsics.width, 3)
    return (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).numpy()


def _render_rays(dense: DenseBake, o: Float[Tensor, "n 3"], d: Float[Tensor, "n 3"]) -> Float[Tensor, "n 3"]:
    h = dense.bake.header
    background = torch.tensor(h.background)
    aabb = torch.tensor(h.aabb, dtype=torch.float32)
    t_near, t_far, hit = intersect_aabb_torch(o, d, aabb)
    n = o.shape[0]
    rgb = torch.zeros(n, 3)
    opacity = torch.zeros(n)
    rays = hit.nonzero()[:, 0]
    if rays.numel():
        length = (t_far - t_near)[rays]
        count = int(math.ceil(float(length.max()) / h.step))
        t = t_near[rays, None] + (torch.arange(count, dtype=torch.float32)[None] + 0.5) * h.step  # [a, s]
        valid = t < t_far[rays, None]
        points = o[rays, None] + t[..., None] * d[rays, None]  # [a, s, 3]
        flat = valid.view(-1).nonzero()[:, 0]
        unit = dense.to_unit(points.view(-1, 3)[flat])
        keep = dense.occupied(unit)
        flat, unit = flat[keep], unit[keep]
        sigma = torch.zeros(valid.numel())
        raw = dense.sample(dense.raw, unit)[:, 0]
        sigma[flat] = F.softplus(raw) * h.density_scale
        weights = weights_from_optical_depth(sigma.view(valid.shape) * h.step)  # [a, s]
        w = weights.view(-1)[flat]
        shade = w > SHADE_WEIGHT
        flat, unit, w = flat[shade], unit[shade], w[shade]
        ray_of = torch.div(flat, valid.shape[1], rounding_mode="floor")
        colours = _colours(dense, unit, d[rays][ray_of], points.view(-1, 3)[flat])
        rgb_hit = torch.zeros(rays.numel(), 3).index_add_(0, ray_of, w[:, None] * colours)
        rgb[rays] = rgb_hit
        opacity[rays] = weights.sum(-1)
    return composite_background(rgb, opacity, background)


def _colours(dense: DenseBake, unit: Float[Tensor, "m 3"], directions: Float[Tensor, "m 3"],
             points: Float[Tensor, "m 3"]) -> Float[Tensor, "m 3"]:
    h = dense.bake.header
    coef = dense.sample(dense.coefficients, unit)  # [m, c]
    probes = None
    if h.shading == "level":
        assert h.normal_step is not None
        probes = dense.sample(dense.raw, dense.to_unit(probe_points(points, h.normal_step)))[:, 0].view(-1, N_PROBES)
    basis = colour_basis(h.shading, h.sh_degree, directions, probes, h.cosine_powers)  # [m, b]
    logits = (coef.view(-1, basis.shape[1], 3) * basis[..., None]).sum(1)
    return torch.sigmoid(logits)
