"""Reference volume renderer for the synthetic ground truth: written for correctness, vectorised.

Independent of the model's renderer. Two kinds of image:
- DVR: emission-absorption along each ray, ``C = sum_i T_i alpha_i c_i + T_n * background`` with
  ``alpha_i = 1 - exp(-sigma_i dt_i)`` and ``T_i = exp(-sum_{j<i} sigma_j dt_j)``, samples at the
  segment midpoints, ``sigma`` and ``c`` from a piecewise-linear TF whose opacities are corrected for
  the step (see ``transfer_function``).
- IR: the first crossing of the isovalue along the ray (field sampled at the segment ends), refined
  by bisection, normals from the field's gradient (central differences), Blinn-Phong shading from a
  headlight; the side of the surface where the field is above the isovalue is the inside.
Cameras follow ``visnerf.data.cameras`` (camera-to-world, OpenGL axes, pixel centres at +0.5).
Nothing here needs autograd; the whole module runs under ``torch.no_grad``.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from jaxtyping import Float
from torch import Tensor
from typing_extensions import assert_never

from visnerf.data.cameras import Intrinsics, image_rays
from visnerf.scenes.raymarch import ray_intervals, uniform_segments
from visnerf.scenes.transfer_function import RGB, TransferFunction

ScalarField = Callable[[Tensor], Tensor]
Box = tuple[tuple[float, float, float], tuple[float, float, float]]


@dataclass(frozen=True)
class DvrVolume:
    """A scalar field seen through a transfer function."""

    field: ScalarField
    """Values ``[n]`` at world points ``[n, 3]``."""
    transfer_function: TransferFunction
    """Colour and opacity over the field's value."""
    bbox: Box = ((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5))
    """The volume's box; rays are marched inside it only."""
    support_radius: float | None = None
    """If set, the field is zero outside the ball of this radius at the origin (rays are clipped)."""
    lit: bool = False
    """Shade each sample's colour with a headlight (Blinn-Phong, ``MarchConfig.shading``) about the
    field's gradient, as volume renderers' shading option does (``lit_colours``): translucent
    layers then show shading and highlights that change with the view."""


@dataclass(frozen=True)
class IsoVolume:
    """The isosurface of a scalar field at one isovalue, shaded as an opaque surface."""

    field: ScalarField
    """Values ``[n]`` at world points ``[n, 3]``."""
    isovalue: float
    """The surface is ``field == isovalue``; the inside is where the field is above it."""
    colour: RGB = (0.9, 0.55, 0.2)
    """Diffuse colour of the outside of the surface."""
    back_colour: RGB = (0.35, 0.55, 0.85)
    """Diffuse colour of the inside (seen where the camera is inside or the box cuts the surface)."""
    bbox: Box = ((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5))
    """The volume's box; rays are marched inside it only."""
    support_radius: float | None = None
    """If set, the field is the same constant outside this ball, so no surface lies there."""


Volume = DvrVolume | IsoVolume


@dataclass(frozen=True)
class ShadingConfig:
    """Blinn-Phong shading with a white headlight at the camera (light = view direction)."""

    ambient: float = 0.2
    """Ambient fraction of the diffuse colour."""
    diffuse: float = 0.75
    """Lambertian weight."""
    specular: float = 0.3
    """Weight of the white highlight."""
    shininess: float = 40.0
    """Blinn-Phong exponent of the half-vector term."""


@dataclass(frozen=True)
class MarchConfig:
    """How the reference renderer marches and shades."""

    step: float = 1.0 / 256.0
    """Target segment length in world units (each ray uses the nearest length that tiles its interval)."""
    samples_per_pass: int = 32
    """Segments evaluated per ray in one vectorised pass."""
    chunk_rays: int = 8192
    """Rays marched together; with ``samples_per_pass`` this bounds the points per field call."""
    early_stop_transmittance: float = 1e-4
    """DVR rays stop once their transmittance falls below this (0 never stops early)."""
    background: RGB = (1.0, 1.0, 1.0)
    """Colour behind the volume."""
    near: float = 0.0
    """Rays start this far from the camera (0: a camera inside the volume sees from its eye)."""
    bisection_steps: int = 20
    """IR: halvings of the bracketing segment."""
    normal_eps: float = 1e-3
    """IR: half the central-difference spacing of the gradient, in world units."""
    shading: ShadingConfig = field(default_factory=ShadingConfig)
    """IR surface shading."""


@dataclass(frozen=True)
class RayOutput:
    """Per-ray results."""

    rgb: Float[Tensor, "n 3"]
    """Colour composited over the background."""
    opacity: Float[Tensor, " n"]
    """1 - transmittance (DVR) or 1 where the surface was hit (IR)."""
    depth: Float[Tensor, " n"]
    """Weighted mean sample distance (DVR) or hit distance (IR); +inf where nothing was met."""


def render_rays(
    volume: Volume,
    rays_o: Float[Tensor, "n 3"],
    rays_d: Float[Tensor, "n 3"],
    config: MarchConfig,
) -> RayOutput:
    """Render unit-direction rays in chunks of ``config.chunk_rays``. Not differentiable."""
    outputs = []
    with torch.no_grad():
        for start in range(0, rays_o.shape[0], config.chunk_rays):
            chunk_o = rays_o[start : start + config.chunk_rays]
            chunk_d = rays_d[start : start + config.chunk_rays]
            match volume:
                case DvrVolume():
                    outputs.append(_render_dvr(volume, chunk_o, chunk_d, config))
                case IsoVolume():
                    outputs.append(_render_iso(volume, chunk_o, chunk_d, config))
                case _:
                    assert_never(volume)
    if not outputs:
        empty = rays_o.new_zeros(0)
        return RayOutput(rays_o.new_zeros(0, 3), empty, empty)
    return RayOutput(
        torch.cat([o.rgb for o in outputs]),
        torch.cat([o.opacity for o in outputs]),
        torch.cat([o.depth for o in outputs]),
    )


def render_image(
    volume: Volume, c2w: Float[Tensor, "4 4"], intrinsics: Intrinsics, config: MarchConfig
) -> RayOutput:
    """Render every pixel of one camera; fields are row-major ``[h * w]`` (reshape to ``[h, w]``)."""
    rays_o, rays_d = image_rays(c2w, intrinsics)  # [h, w, 3]
    return render_rays(volume, rays_o.reshape(-1, 3), rays_d.reshape(-1, 3), config)


def _intervals(
    volume: Volume, rays_o: Tensor, rays_d: Tensor, config: MarchConfig
) -> tuple[Tensor, Tensor, Tensor]:
    """Per ray: start distance, segment count (0: misses the volume) and segment length."""
    t_near, t_far, valid = ray_intervals(
        rays_o, rays_d, volume.bbox[0], volume.bbox[1], volume.support_radius, config.near
    )
    count, delta = uniform_segments(t_near, t_far, valid, config.step)
    return t_near, count, delta


def _background(config: MarchConfig, like: Tensor) -> Tensor:
    return torch.tensor(config.background, dtype=like.dtype, device=like.device)


def _render_dvr(volume: DvrVolume, rays_o: Tensor, rays_d: Tensor, config: MarchConfig) -> RayOutput:
    t_near, count, delta = _intervals(volume, rays_o, rays_d, config)
    n, s = rays_o.shape[0], config.samples_per_pass
    rgb = rays_o.new_zeros(n, 3)
    depth_sum = rays_o.new_zeros(n)
    optical_depth = rays_o.new_zeros(n)
    eps = config.early_stop_transmittance
    stop_depth = -math.log(eps) if eps > 0 else math.inf
    offsets = torch.arange(s, device=rays_o.device)  # [s]
    ids = torch.nonzero(count > 0).squeeze(1)  # [m] rays still marching, with their state below
    o, d, t0, dt, cnt = rays_o[ids], rays_d[ids], t_near[ids, None], delta[ids, None], count[ids, None]
    acc_rgb, acc_depth, acc_tau = rgb[ids], depth_sum[ids], optical_depth[ids]
    start = 0
    while ids.numel() > 0:
        m = ids.numel()
        index = start + offsets[: min(s, int(cnt.max()) - start)]  # [s'] no slot past the longest ray
        t_mid = t0 + (index + 0.5).to(dt.dtype) * dt  # [m, s']
        points = o[:, None, :] + t_mid[..., None] * d[:, None, :]  # [m, s', 3]
        values = volume.field(points.reshape(-1, 3))  # [m * s']
        colour, sigma = volume.transfer_function.colour_and_extinction(values)
        if volume.lit:
            directions = d[:, None, :].expand(-1, index.numel(), -1).reshape(-1, 3)
            colour = lit_colours(volume.field, points.reshape(-1, 3), directions, colour, sigma, config)
        tau = sigma.reshape(m, -1) * dt  # [m, s']
        if int(cnt.min()) < start + index.numel():  # some rays end inside this pass
            tau = torch.where(index < cnt, tau, torch.zeros_like(dt))
        # [m, s'] exclusive optical depth as a shifted cumulative sum (never ``cumsum - tau``, which
        # cancels in float32 after a large term); written out here, not imported from the model's
        # rendering/volume.py, so that the ground truth stays independent of the renderer it judges.
        shifted = torch.cumsum(tau[:, :-1], dim=1)
        before = acc_tau[:, None] + torch.cat([torch.zeros_like(tau[:, :1]), shifted], dim=1)
        weights = torch.exp(-before) * -torch.expm1(-tau)  # [m, s']
        acc_rgb = acc_rgb + torch.einsum("ms,msc->mc", weights, colour.reshape(m, -1, 3))
        acc_depth = acc_depth + (weights * t_mid).sum(dim=1)
        acc_tau = acc_tau + tau.sum(dim=1)
        start += index.numel()
        keep = (cnt[:, 0] > start) & (acc_tau < stop_depth)  # [m]
        if not bool(keep.all()):
            done = ids[~keep]
            rgb[done], depth_sum[done], optical_depth[done] = acc_rgb[~keep], acc_depth[~keep], acc_tau[~keep]
            ids, o, d, t0, dt, cnt = ids[keep], o[keep], d[keep], t0[keep], dt[keep], cnt[keep]
            acc_rgb, acc_depth, acc_tau = acc_rgb[keep], acc_depth[keep], acc_tau[keep]
    transmittance = torch.exp(-optical_depth)  # [n]
    opacity = 1.0 - transmittance
    rgb = rgb + transmittance[:, None] * _background(config, rgb)
    depth = torch.where(opacity > 0, depth_sum / opacity.clamp_min(torch.finfo(opacity.dtype).tiny), math.inf)
    return RayOutput(rgb, opacity, depth)


def _offset_from_isovalue(volume: IsoVolume, points: Tensor) -> Tensor:
    return volume.field(points.reshape(-1, 3)).reshape(points.shape[:-1]) - volume.isovalue


def _render_iso(volume: IsoVolume, rays_o: Tensor, rays_d: Tensor, config: MarchConfig) -> RayOutput:
    t_near, count, delta = _intervals(volume, rays_o, rays_d, config)
    n, s = rays_o.shape[0], config.samples_per_pass
    t_lo = rays_o.new_zeros(n)  # bracket [t_lo, t_lo + delta] of the first crossing
    hit = torch.zeros(n, dtype=torch.bool, device=rays_o.device)
    offsets = torch.arange(1, s + 1, device=rays_o.device)  # [s]
    ids = torch.nonzero(count > 0).squeeze(1)  # [m] rays still searching, with their state below
    o, d, t0, dt, cnt = rays_o[ids], rays_d[ids], t_near[ids, None], delta[ids, None], count[ids, None]
    previous = _offset_from_isovalue(volume, o + t0 * d)  # [m] at node 0, the entry point
    start = 0
    while ids.numel() > 0:
        index = start + offsets[: min(s, int(cnt.max()) - start)]  # [s'] node indices
        t_node = t0 + index.to(dt.dtype) * dt  # [m, s']
        g = _offset_from_isovalue(volume, o[:, None, :] + t_node[..., None] * d[:, None, :])  # [m, s']
        inside = torch.cat([previous[:, None], g], dim=1) > 0  # [m, s' + 1]
        crossing = (inside[:, 1:] != inside[:, :-1]) & (index <= cnt)  # [m, s']
        found = crossing.any(dim=1)  # [m]
        first = torch.argmax(crossing.to(torch.uint8), dim=1)  # [m] first crossing in this pass
        hit[ids[found]] = True
        t_lo[ids[found]] = (t0 + (start + first[:, None]).to(dt.dtype) * dt)[found, 0]
        start += index.numel()
        keep = ~found & (cnt[:, 0] > start)  # [m]
        ids, o, d, t0, dt, cnt, previous = (
            ids[keep],
            o[keep],
            d[keep],
            t0[keep],
            dt[keep],
            cnt[keep],
            g[keep, -1],
        )
    rays = torch.nonzero(hit).squeeze(1)
    t_hit = _bisect(volume, rays_o[rays], rays_d[rays], t_lo[rays], delta[rays], config.bisection_steps)
    rgb = _background(config, rays_o).expand(n, 3).clone()
    rgb[rays] = _shade(volume, rays_o[rays] + t_hit[:, None] * rays_d[rays], rays_d[rays], config)
    depth = torch.full_like(t_lo, math.inf)
    depth[rays] = t_hit
    return RayOutput(rgb, hit.to(rays_o.dtype), depth)


def _bisect(
    volume: IsoVolume, rays_o: Tensor, rays_d: Tensor, t_a: Tensor, delta: Tensor, steps: int
) -> Tensor:
    """Halve ``[t_a, t_a + delta]``, which brackets a sign change of field - isovalue, ``steps`` times."""
    t_b = t_a + delta
    inside_a = _offset_from_isovalue(volume, rays_o + t_a[:, None] * rays_d) > 0  # [m]
    for _ in range(steps):
        t_mid = 0.5 * (t_a + t_b)
        same = (_offset_from_isovalue(volume, rays_o + t_mid[:, None] * rays_d) > 0) == inside_a  # [m]
        t_a = torch.where(same, t_mid, t_a)
        t_b = torch.where(same, t_b, t_mid)
    return 0.5 * (t_a + t_b)


def field_gradient(field: ScalarField, points: Float[Tensor, "n 3"], eps: float) -> Float[Tensor, "n 3"]:
    """Central-difference gradient of ``field`` with spacing ``2 * eps``."""
    step = eps * torch.eye(3, dtype=points.dtype, device=points.device)  # [3, 3]
    probes = torch.cat([points[:, None, :] + step, points[:, None, :] - step], dim=1)  # [n, 6, 3]
    values = field(probes.reshape(-1, 3)).reshape(-1, 6)  # [n, 6]
    return (values[:, :3] - values[:, 3:]) / (2.0 * eps)


def lit_colours(
    field: ScalarField, points: Float[Tensor, "n 3"], rays_d: Float[Tensor, "n 3"], colour: Float[Tensor, "n 3"],
    sigma: Float[Tensor, " n"], config: MarchConfig,
) -> Float[Tensor, "n 3"]:
    """The transfer function's colours of a lit volume: Blinn-Phong with a headlight about the
    field's gradient (central differences, only where the extinction is not zero), two-sided, with
    a white highlight, clamped to [0, 1]. A flat field (zero gradient) shades as facing the eye."""
    shading = config.shading
    out = colour.clone()
    seen = (sigma > 0).nonzero()[:, 0]
    if seen.numel() == 0:
        return out
    grad = field_gradient(field, points[seen], config.normal_eps)  # [m, 3]
    norm = torch.linalg.norm(grad, dim=-1)  # [m]
    facing = (grad * rays_d[seen]).sum(dim=-1).abs() / norm.clamp_min(torch.finfo(norm.dtype).tiny)
    cos_light = torch.where(norm > 0, facing, torch.ones_like(facing)).clamp(max=1.0)[:, None]  # [m, 1]
    highlight = shading.specular * cos_light**shading.shininess
    out[seen] = (colour[seen] * (shading.ambient + shading.diffuse * cos_light) + highlight).clamp(0.0, 1.0)
    return out


def _shade(volume: IsoVolume, points: Tensor, rays_d: Tensor, config: MarchConfig) -> Tensor:
    shading = config.shading
    outward = -field_gradient(volume.field, points, config.normal_eps)  # [m, 3] field grows inwards
    norm = torch.linalg.norm(outward, dim=-1, keepdim=True)  # [m, 1]
    outward = torch.where(norm > 0, outward / norm.clamp_min(torch.finfo(norm.dtype).tiny), -rays_d)
    to_eye = -rays_d  # [m, 3] headlight: light, view and half vector coincide
    facing = (outward * to_eye).sum(dim=-1)  # [m]
    front = facing >= 0
    cos_light = facing.abs()[:, None]  # [m, 1] the normal is flipped to face the camera
    colour = torch.where(
        front[:, None],
        torch.tensor(volume.colour, dtype=points.dtype, device=points.device),
        torch.tensor(volume.back_colour, dtype=points.dtype, device=points.device),
    )  # [m, 3]
    highlight = shading.specular * cos_light**shading.shininess  # [m, 1]
    lit = colour * (shading.ambient + shading.diffuse * cos_light) + highlight
    return lit.clamp(0.0, 1.0)
