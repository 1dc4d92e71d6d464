"""The training path's render: stratified samples placed on a batch of rays, those behind opaque
content dropped, one differentiable pass (``shade_rays``). The fused CPU step renders the same with
compiled loops (``compact_render``); this is every device's path and its twin in the tests."""

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from visnerf.rendering.aabb import intersect_aabb
from visnerf.rendering.colour_sampling import ColourSampling, pick_coloured
from visnerf.rendering.density_gradients import DensityGradientSampling, density_with_sampled_gradients
from visnerf.rendering.occupancy import query_occupancy
from visnerf.rendering.render_settings import RenderSettings
from visnerf.rendering.sampling import uniform_noise, uniform_samples
from visnerf.rendering.volume import exclusive_optical_depth, optical_depths, weights_from_optical_depth
from visnerf.representation.field import VisNerfField

if TYPE_CHECKING:
    pass


def _shade_samples(
    field: VisNerfField,
    rays_d: Float[Tensor, "n 3"],
    points: Float[Tensor, "n s 3"],
    deltas: Float[Tensor, "n s"],
    valid: Bool[Tensor, "n s"],
    q_density: Float[Tensor, "n d"],
    q_appearance: Float[Tensor, "n c"],
    tau_before: Float[Tensor, " n"],
    weight_threshold: float,
    density_grads: DensityGradientSampling | None = None,
    sigma: Float[Tensor, "n s"] | None = None,
    colour_sampling: ColourSampling | None = None,
) -> tuple[Float[Tensor, "n 3"], Float[Tensor, " n"], Float[Tensor, "n s"]]:
    """Density at valid samples, log-space transmittance, colour where the weight matters.

    Returns (colour contribution, optical depth of this segment, weights). ``tau_before`` is the
    optical depth accumulated by earlier segments of the same rays. With ``density_grads``, the
    backward pass takes near-empty samples at random (``rendering.density_gradients``), from the
    graph-free densities ``sigma`` where they are given. With ``colour_sampling``, light samples
    are coloured at random (``rendering.colour_sampling``).
    """
    n, s = valid.shape
    # Gathers by index_select on flat sample indices: the backward of advanced indexing is
    # index_put_(accumulate=True), several times slower on the CPU than index_select's index_add.
    flat_points = points.reshape(-1, 3)
    flat = valid.reshape(-1).nonzero()[:, 0]  # [m], into the n * s samples
    sigmas = torch.zeros(n * s, dtype=points.dtype, device=points.device)
    if flat.numel() > 0:
        ray_idx = torch.div(flat, s, rounding_mode="floor")
        sel_points, sel_q = flat_points.index_select(0, flat), q_density.index_select(0, ray_idx)
        if density_grads is None:
            dens = field.density(sel_points, sel_q)
        else:
            known = None if sigma is None else sigma.reshape(-1).index_select(0, flat)
            dens = density_with_sampled_gradients(
                field.density, sel_points, sel_q, deltas.reshape(-1).index_select(0, flat), density_grads, known)
        sigmas = sigmas.index_copy(0, flat, dens)
    sigmas = sigmas.view(n, s)
    tau = optical_depths(sigmas, deltas)  # [n, s]
    weights = weights_from_optical_depth(tau, tau_before)  # [n, s]
    shade = (valid & (weights > weight_threshold)).reshape(-1).nonzero()[:, 0]  # [k], into the n * s samples
    shade, shade_weights = pick_coloured(weights.reshape(-1), shade, colour_sampling)
    rgb = torch.zeros(n, 3, dtype=points.dtype, device=points.device)
    if shade.numel() > 0:
        shade_rays = torch.div(shade, s, rounding_mode="floor")
        shade_points, shade_dirs = flat_points.index_select(0, shade), rays_d.index_select(0, shade_rays)
        if field.levels is None:
            colors = field.color(shade_points, shade_dirs, q_appearance.index_select(0, shade_rays))  # [k, 3]
        else:  # the level field's normal needs the density features too
            colors = field.color(shade_points, shade_dirs, q_appearance.index_select(0, shade_rays),
                                 q_density.index_select(0, shade_rays))
        rgb = rgb.index_add(0, shade_rays, shade_weights[:, None] * colors)
    return rgb, tau.sum(dim=-1), weights


@dataclass(frozen=True)
class RaySamples:
    """Where a batch of rays is sampled, before shading (``place_samples``)."""

    points: Float[Tensor, "n s 3"]
    deltas: Float[Tensor, "n s"]
    valid: Bool[Tensor, "n s"]
    """The samples evaluated: in the box, in the ray's window and in an occupied cell (and, after
    ``drop_occluded``, not behind an opaque part of the ray)."""
    sigma: Float[Tensor, "n s"] | None = None
    """Densities at the valid samples computed without a graph (``drop_occluded``), 0 elsewhere;
    the shading pass reuses them where it back-propagates only some samples."""

    def of_rays(self, rays: slice) -> "RaySamples":
        sigma = None if self.sigma is None else self.sigma[rays]
        return RaySamples(self.points[rays], self.deltas[rays], self.valid[rays], sigma)

    def per_ray(self) -> Int[Tensor, " n"]:
        """Samples evaluated per ray."""
        return self.valid.sum(dim=1)


@torch.no_grad()
def place_samples(
    field: VisNerfField,
    rays_o: Float[Tensor, "n 3"],
    rays_d: Float[Tensor, "n 3"],
    step: float,
    max_samples: int,
    occupancy: Bool[Tensor, "x y z"] | None,
    generator: torch.Generator | None = None,
    windows: tuple[Int[Tensor, " n"], Int[Tensor, " n"]] | None = None,
) -> RaySamples:
    """The training path's sample positions (no gradient flows through them).

    Stratified when ``generator`` is given: sample ``i`` of a ray at ``t_near + step * (i + u)``,
    one ``u`` per ray. ``windows`` (first, last), from ``EmptySpace.sample_window(..., near=1)``,
    restricts each ray to samples ``first .. last``: the samples left out lie in empty cells,
    which the occupancy test would drop anyway.
    """
    t_near, t_far, hit = intersect_aabb(rays_o, rays_d, field.aabb)
    span = float((t_far - t_near).max()) if hit.any() else 0.0
    n_samples = max(1, min(max_samples, math.ceil(span / step)))
    jitter = None
    if generator is not None:
        jitter = uniform_noise((rays_o.shape[0],), generator, rays_o.device)
    if windows is None:
        t = uniform_samples(t_near, n_samples, step, jitter)  # [n, s]
        valid = (t < t_far[:, None]) & hit[:, None]
    else:
        start = windows[0].clamp_min(0)
        stop = windows[1].clamp_max(n_samples - 1)
        longest = max(1, int((stop - start + 1).max()))
        index = start[:, None] + torch.arange(longest, device=rays_o.device)[None]  # [n, s]
        u = torch.full_like(t_near, 0.5) if jitter is None else jitter
        t = t_near[:, None] + step * (index.to(t_near.dtype) + u[:, None])
        valid = (index <= stop[:, None]) & (t < t_far[:, None]) & hit[:, None]
    deltas = torch.full_like(t, step)
    points = rays_o[:, None, :] + rays_d[:, None, :] * t[..., None]  # [n, s, 3]
    if occupancy is not None:
        valid = valid.masked_scatter(valid, query_occupancy(occupancy, field.aabb, points[valid]))
    return RaySamples(points, deltas, valid)


@torch.no_grad()
def drop_occluded(
    field: VisNerfField,
    samples: RaySamples,
    params: Float[Tensor, "n k"],
    stop_eps: float,
    first_segment: int = RenderSettings.first_segment_samples,
    q_density: Float[Tensor, "n d"] | None = None,
) -> RaySamples:
    """``samples`` without those a ray reaches with transmittance below ``stop_eps`` (hidden
    behind opaque content), with the densities of the samples kept, evaluated without a graph.

    A dropped sample's weight is below ``stop_eps``, and so is every later one's, so the render
    changes by at most ``stop_eps`` times the colour range. Behind an opaque isosurface every
    sample of the ray's occupied window lies in the surface's inside, which the visual hull and
    the density both count as content; this keeps the differentiable pass to the samples in front
    of it. The rays are marched in segments (``first_segment`` samples, then doubling, as the
    inference renderer does) and a ray's densities are evaluated only up to the segment in which
    it turns opaque. ``stop_eps`` 0 keeps every sample and evaluates none: ``samples`` come back as
    they are (the shading pass evaluates their densities itself). ``q_density``: the rays' density
    parameter features where the caller has them (else computed from ``params``)."""
    if stop_eps <= 0.0:
        return samples
    n, s = samples.valid.shape
    dtype, device = samples.points.dtype, samples.points.device
    sigma = torch.zeros(n, s, dtype=dtype, device=device)
    visible = torch.zeros_like(samples.valid)
    q_d = field.param_features(params)[0] if q_density is None else q_density
    tau_stop = -math.log(stop_eps) if stop_eps > 0.0 else math.inf
    tau_before = torch.zeros(n, dtype=dtype, device=device)
    active = samples.valid.any(dim=1).nonzero()[:, 0]  # [a] rays still marching
    start, seg = 0, first_segment
    while start < s and active.numel() > 0:
        stop = min(s, start + seg)
        valid = samples.valid[:, start:stop].index_select(0, active)  # [a, g]
        flat = valid.reshape(-1).nonzero()[:, 0]  # [m], into the a * g samples
        g = stop - start
        seg_sigma = torch.zeros(active.numel() * g, dtype=dtype, device=device)
        if flat.numel() > 0:
            ray = active.index_select(0, flat // g)
            points = samples.points[:, start:stop].index_select(0, active).reshape(-1, 3).index_select(0, flat)
            seg_sigma.index_copy_(0, flat, field.density(points, q_d.index_select(0, ray)).to(dtype))
        seg_sigma = seg_sigma.view(-1, g)
        tau = optical_depths(seg_sigma, samples.deltas[:, start:stop].index_select(0, active))  # [a, g]
        before = tau_before.index_select(0, active)[:, None] + exclusive_optical_depth(tau)
        seen = valid & (before < tau_stop)
        sigma[active, start:stop] = seg_sigma * seen
        visible[active, start:stop] = seen
        tau_before.index_add_(0, active, tau.sum(dim=1))
        later = samples.valid[:, stop:].index_select(0, active).any(dim=1)
        active = active[(tau_before.index_select(0, active) < tau_stop) & later]
        start, seg = stop, 2 * seg
    return RaySamples(samples.points, samples.deltas, visible, sigma)


def shade_rays(
    field: VisNerfField,
    rays_d: Float[Tensor, "n 3"],
    params: Float[Tensor, "n k"],
    background: Float[Tensor, "n 3"],
    samples: RaySamples,
    weight_threshold: float = 1e-4,
    density_grads: DensityGradientSampling | None = None,
    colour_sampling: ColourSampling | None = None,
    features: tuple[Float[Tensor, "n d"], Float[Tensor, "n c"]] | None = None,
) -> dict[str, Tensor]:
    """Differentiable colour of rays at their ``samples``. ``density_grads`` back-propagates
    near-empty samples at random, unbiased (``rendering.density_gradients``); ``colour_sampling``
    colours light samples at random, unbiased (``rendering.colour_sampling``). Returns ``rgb``
    [n, 3], ``opacity`` [n] and ``n_samples`` (valid samples evaluated). ``features``: the rays'
    (density, appearance) parameter features where the caller has them (else from ``params``)."""
    q_d, q_a = field.param_features(params) if features is None else features
    tau0 = torch.zeros(rays_d.shape[0], dtype=rays_d.dtype, device=rays_d.device)
    rgb, tau, _ = _shade_samples(field, rays_d, samples.points, samples.deltas, samples.valid, q_d, q_a, tau0,
                                 weight_threshold, density_grads, samples.sigma, colour_sampling)
    opacity = -torch.expm1(-tau)
    return {
        "rgb": rgb + background * (1.0 - opacity)[:, None],
        "opacity": opacity,
        "n_samples": samples.valid.sum(),
    }


def render_rays(
    field: VisNerfField,
    rays_o: Float[Tensor, "n 3"],
    rays_d: Float[Tensor, "n 3"],
    params: Float[Tensor, "n k"],
    background: Float[Tensor, "n 3"],
    step: float,
    max_samples: int,
    occupancy: Bool[Tensor, "x y z"] | None,
    weight_threshold: float = 1e-4,
    generator: torch.Generator | None = None,
    windows: tuple[Int[Tensor, " n"], Int[Tensor, " n"]] | None = None,
    density_grads: DensityGradientSampling | None = None,
    colour_sampling: ColourSampling | None = None,
) -> dict[str, Tensor]:
    """Differentiable render of a batch of rays (training and tests): ``place_samples`` then
    ``shade_rays``."""
    samples = place_samples(field, rays_o, rays_d, step, max_samples, occupancy, generator, windows)
    return shade_rays(field, rays_d, params, background, samples, weight_threshold, density_grads, colour_sampling)
