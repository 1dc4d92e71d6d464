"""Wires sampler, field and compositing: rays in, colours out.

``render_rays`` is the training path (stratified samples, the ones behind opaque content dropped,
one differentiable pass). ``render_image`` is the inference path: deterministic samples on a lattice
one step apart; each ray walks only the window between its first and last sample in an occupied
cell (found by jumping over empty blocks, ``rendering.empty_space``), in segments, testing each
sample's cell, until it leaves the window or its transmittance falls below ``early_stop_eps``.
Chunks of rays are marched on one thread per core (``rendering.parallel``). On the CPU the walk,
each segment's placing and compositing, and the decoders' input rows are compiled loops
(``empty_space_kernel``, ``march_kernel``, ``representation.vm_kernel``); other devices run the
same steps as torch operations.
"""

import math
import weakref
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float, Int
from torch import Tensor

from visnerf.config import RenderConfig
from visnerf.data.cameras import Intrinsics, image_rays
from visnerf.rendering import march_kernel
from visnerf.rendering.aabb import intersect_aabb
from visnerf.rendering.cancel import CancelCheck, raise_if_cancelled
from visnerf.rendering.colour_sampling import ColourSampling, pick_coloured
from visnerf.rendering.density_gradients import DensityGradientSampling, density_with_sampled_gradients
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.occupancy import query_occupancy
from visnerf.rendering.parallel import chunk_workers, map_chunks
from visnerf.rendering.sampling import uniform_noise, uniform_samples
from visnerf.rendering.volume import exclusive_optical_depth, optical_depths, weights_from_optical_depth
from visnerf.representation.field import VisNerfField
from visnerf.representation.frame_field import FrameField, SampleTaps
from visnerf.runtime import batch_factor, bf16_native

if TYPE_CHECKING:
    from visnerf.checkpoint import CheckpointMeta


EXHAUSTIVE_STEP_RATIO = 0.5
"""Sample spacing of the exhaustive reference, in voxels, at most: the paper's training spacing."""


EXHAUSTIVE_CHUNK_RAYS = 1024
"""Rays per chunk of an exhaustive frame: every sample of every ray is shaded, so a chunk's
buffers grow with its rays times its segment; fewer rays bound the memory and cost no time (the
end of training renders such frames to choose the spacing; docs/decisions.md, "Rendering")."""


BLOCK_RAYS = 262144
"""Rays of a frame made, walked and marched at a time (``render_image``), 512x512 pixels: the
empty-space walk runs on all of a block's rays at once, and a whole 1440x1440 frame at once
(2 million rays) raised peak memory by 1.0 to 1.3 GB over the loaded model, in blocks by 0.35 to
0.40 GB, in about the same time; a frame of at most this many rays is one block, as before
(bench/results/render_memory.md)."""


def rays_per_chunk(settings: "RenderSettings", device: torch.device) -> int:
    """Rays a chunk of a frame holds on ``device``: ``settings.chunk_rays`` on the CPU, where
    chunks go to one thread per core; more on a GPU (``runtime.batch_factor``)."""
    return settings.chunk_rays * batch_factor(device)


def exhaustive_step_ratio(cfg: RenderConfig) -> float:
    """The exhaustive reference's spacing: the finer of the training spacing and half a voxel, so
    that a model trained with coarser samples is still judged against finely sampled frames."""
    return min(cfg.step_ratio, EXHAUSTIVE_STEP_RATIO)


@dataclass(frozen=True)
class RenderSettings:
    """Settings of one render call (derived from the checkpoint's RenderConfig and a quality)."""

    step_ratio: float = 0.5
    max_samples: int = 1024
    weight_threshold_per_voxel: float = 1e-4
    """Samples whose compositing weight is at most this times ``step_ratio`` skip colour decoding
    (``RenderConfig.full_weight_threshold_per_voxel``); 0 decodes every sample."""
    early_stop_eps: float = 1e-4
    chunk_rays: int = 4096
    """Rays per chunk of a frame (inference); chunks are marched one per thread on the CPU."""
    segment_samples: int = 128
    """Samples marched per segment before finished rays are dropped (inference). With two threads on
    an idle machine, 4096 rays by 128 samples rendered 256x256 frames of the bundled checkpoints and
    Nyx in 322 / 739 / 439 ms (medians of 8 views) against 354 / 765 / 527 ms at 2048 by 64 and
    452 ms (Nyx) at 8192 by 128. The chunk size used to be stored in checkpoints; it belongs to the
    machine, not the model, and a stored value is ignored."""
    first_segment_samples: int = 16
    """Samples in a ray's first segment; each later one doubles, up to ``segment_samples``. Rays
    that turn opaque early (surfaces) then stop without marching a whole long segment."""
    resolution_scale: float = 1.0
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    use_occupancy: bool = True
    early_termination: bool = True
    bf16: bool = False
    """Decoder matrix products in bfloat16 where the device has bf16 matrix units (inference)."""
    threaded_chunks: bool = True
    """On the CPU, march chunks of rays on one thread per core (``rendering.parallel``)."""

    @classmethod
    def from_config(
        cls, cfg: RenderConfig, background: tuple[float, float, float], quality: str = "full"
    ) -> "RenderSettings":
        """``full``: as the server renders; ``preview``: smaller and coarser; ``exhaustive``: the
        plain reference (``exhaustive_step_ratio``, every sample in the model's occupancy grid,
        float32).

        The reference marches the grid because the grid is part of the model: training fits only
        the cells it keeps, and outside them the density has had no photometric loss since the grid
        was last narrowed, and marched everywhere the reference scores far under the frames it
        judges (docs/decisions.md, "Rendering"; ``evaluation.spacing``)."""
        if quality not in ("full", "preview", "exhaustive"):
            raise ValueError(f"quality must be 'full', 'preview' or 'exhaustive', got {quality!r}")
        settings = cls(
            step_ratio=cfg.full_step_ratio,
            max_samples=cfg.max_samples,
            weight_threshold_per_voxel=cfg.full_weight_threshold_per_voxel,
            early_stop_eps=cfg.early_stop_eps,
            background=background,
            bf16=cfg.bf16,
        )
        if quality == "exhaustive":
            settings = replace(settings, step_ratio=exhaustive_step_ratio(cfg), early_termination=False,
                               weight_threshold_per_voxel=0.0, bf16=False, chunk_rays=EXHAUSTIVE_CHUNK_RAYS)
        elif quality == "preview":
            settings = replace(
                settings,
                step_ratio=exhaustive_step_ratio(cfg) * cfg.preview_step_factor,
                resolution_scale=cfg.preview_scale,
            )
        return settings

    @classmethod
    def from_meta(cls, meta: "CheckpointMeta", quality: str = "full") -> "RenderSettings":
        return cls.from_config(meta.render, tuple(meta.background), quality)  # type: ignore[arg-type]


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


def _shade_frame_samples(
    frame: FrameField,
    ray_terms: Float[Tensor, "n h"],
    rays: Int[Tensor, " a"],
    points: Float[Tensor, "a s 3"],
    step: float,
    valid: Bool[Tensor, "a s"],
    tau_before: Float[Tensor, " a"],
    weight_threshold: float,
    rgbw: Float[Tensor, "n 4"],
) -> Float[Tensor, " a"]:
    """Inference twin of ``_shade_samples`` at one parameter tuple, equal spacing ``step``, for
    the segment ``points`` of rays ``rays`` (indices into ``ray_terms`` and ``rgbw``).

    The VM taps of the valid samples are computed once; colour reuses those of the samples whose
    weight matters. Adds the segment's weighted colour and the weight of its shaded samples into
    ``rgbw`` (columns r, g, b, weight); returns its optical depth per ray.
    """
    a, s = valid.shape
    flat = valid.view(-1).nonzero()[:, 0]  # [m], into the a * s samples
    if flat.numel() == 0:
        return torch.zeros(a, dtype=points.dtype, device=points.device)
    samples = frame.lookup(points.view(-1, 3).index_select(0, flat))
    sigmas = torch.zeros(a * s, dtype=points.dtype, device=points.device)
    sigmas = sigmas.index_copy_(0, flat, frame.density_at(samples)).view(a, s)
    tau = sigmas * step  # [a, s]
    weights = weights_from_optical_depth(tau, tau_before)  # [a, s]
    valid_weights = weights.view(-1).index_select(0, flat)  # [m]
    shade = (valid_weights > weight_threshold).nonzero()[:, 0]  # into the valid samples
    _add_shaded_colours(frame, ray_terms, rays, samples, flat, s, valid_weights, shade, rgbw)
    return tau.sum(dim=-1)


def _add_shaded_colours(
    frame: FrameField,
    ray_terms: Float[Tensor, "n h"],
    rays: Int[Tensor, " a"],
    samples: SampleTaps,
    flat: Int[Tensor, " m"],
    seg: int,
    weights: Float[Tensor, " m"],
    shade: Int[Tensor, " k"],
    rgbw: Float[Tensor, "n 4"],
) -> None:
    """Add the weighted colour and the weight of samples ``shade`` (indices into the segment's
    valid ``samples``, whose flat indices are ``flat``: ``ray * seg + j``) into ``rgbw``."""
    if shade.numel() == 0:
        return
    ray_idx = rays.index_select(0, flat.index_select(0, shade) // seg)
    colors = frame.color_at(samples.select(shade), ray_terms.index_select(0, ray_idx))  # [k, 3]
    if march_kernel.available(rgbw.device) and rgbw.dtype == torch.float32:
        march_kernel.accumulate(rgbw, ray_idx, weights, shade, colors)
        return
    shaded = weights.index_select(0, shade)[:, None]  # [k, 1]
    rgbw.index_add_(0, ray_idx, torch.cat([shaded * colors, shaded], dim=1))


def _shade_placed_samples(
    frame: FrameField,
    ray_terms: Float[Tensor, "n h"],
    rays: Int[Tensor, " a"],
    points: Float[Tensor, "m 3"],
    flat: Int[Tensor, " m"],
    seg: int,
    step: float,
    tau: Float[Tensor, " a"],
    weight_threshold: float,
    rgbw: Float[Tensor, "n 4"],
) -> None:
    """``_shade_frame_samples`` for the compacted valid samples of a segment (``march_kernel.place``:
    ``flat`` is ``ray * seg + j``): composited by ``march_kernel.composite``, which advances ``tau``
    in place."""
    if flat.numel() == 0:
        return
    samples = frame.lookup(points)
    weights, shade = march_kernel.composite(flat, frame.density_at(samples), seg, step, tau, weight_threshold)
    _add_shaded_colours(frame, ray_terms, rays, samples, flat, seg, weights, shade, rgbw)


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
    first_segment: int = 16,
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
    they are (the shading pass evaluates their densities itself)."""
    if stop_eps <= 0.0:
        return samples
    n, s = samples.valid.shape
    dtype, device = samples.points.dtype, samples.points.device
    sigma = torch.zeros(n, s, dtype=dtype, device=device)
    visible = torch.zeros_like(samples.valid)
    q_d, _ = field.param_features(params)
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
) -> dict[str, Tensor]:
    """Differentiable colour of rays at their ``samples``. ``density_grads`` back-propagates
    near-empty samples at random, unbiased (``rendering.density_gradients``); ``colour_sampling``
    colours light samples at random, unbiased (``rendering.colour_sampling``). Returns ``rgb``
    [n, 3], ``opacity`` [n] and ``n_samples`` (valid samples evaluated)."""
    q_d, q_a = field.param_features(params)
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


_EMPTY_SPACE: "weakref.WeakKeyDictionary[VisNerfField, tuple[Tensor, EmptySpace]]" = weakref.WeakKeyDictionary()


def empty_space_of(field: VisNerfField) -> EmptySpace | None:
    """The field's occupancy grid with distances to content, built once per grid (cached)."""
    grid = field.occupancy
    if grid is None:
        return None
    cached = _EMPTY_SPACE.get(field)
    if cached is None or cached[0] is not grid:
        cached = (grid, EmptySpace.of(grid, field.aabb))
        _EMPTY_SPACE[field] = cached
    return cached[1]


@dataclass(frozen=True)
class RayWindows:
    """Per ray: the box interval and the window ``[first, last]`` of lattice samples
    ``t_near + step * (i + 0.5)`` to walk (``first > last``: nothing to walk)."""

    t_near: Float[Tensor, " n"]
    t_far: Float[Tensor, " n"]
    first: Int[Tensor, " n"]
    last: Int[Tensor, " n"]

    def __getitem__(self, index: slice) -> "RayWindows":
        return RayWindows(self.t_near[index], self.t_far[index], self.first[index], self.last[index])


def ray_windows(
    field: VisNerfField,
    rays_o: Float[Tensor, "n 3"],
    rays_d: Float[Tensor, "n 3"],
    step: float,
    max_samples: int | None,
    empty_space: EmptySpace | None,
    near: int = 0,
    cancel: CancelCheck | None = None,
) -> RayWindows:
    """Box interval of every ray and its window of lattice samples (``t_near + step * (i + 0.5)``):
    the whole lattice inside the box (at most ``max_samples`` unless None), narrowed to the span
    of the samples in occupied cells when ``empty_space`` is given (``near = 1``: within one cell
    of an occupied one, ``EmptySpace.sample_window``, which asks ``cancel`` between its jumps)."""
    t_near, t_far, hit = intersect_aabb(rays_o, rays_d, field.aabb)
    count = torch.ceil((t_far - t_near) / step - 0.5 + 1e-3).clamp_min(0)  # may count one beyond t_far
    if max_samples is not None:
        count = count.clamp_max(max_samples)
    last = torch.where(hit, count.long() - 1, -1)
    first = torch.zeros_like(last)
    if empty_space is not None:
        first, last = empty_space.sample_window(rays_o, rays_d, t_near, step, first, last, near, cancel)
    return RayWindows(t_near, t_far, first, last)


def render_image(
    field: VisNerfField,
    c2w: Float[Tensor, "4 4"],
    intrinsics: Intrinsics,
    params: Float[Tensor, " k"],
    settings: RenderSettings,
    empty_space: EmptySpace | None = None,
    cancel: CancelCheck | None = None,
) -> Float[Tensor, "h w 3"]:
    """Render one image at normalised parameters (inference; call under ``torch.inference_mode``).

    ``empty_space`` replaces the field's union grid (a grid for these parameters,
    ``rendering.setting_occupancy``); it is ignored when the settings use no occupancy.
    ``cancel`` is asked between the jumps of the empty-space walk that finds the rays' sample
    windows and before each chunk of rays; once it answers True the render stops with
    ``RenderCancelled`` (``rendering.cancel``).

    The frame goes in blocks of whole image rows, about ``BLOCK_RAYS`` rays each: a block's rays
    are made, walked and marched before the next block's, so the memory a frame needs beside its
    output does not grow with the frame."""
    height, width = intrinsics.height, intrinsics.width
    raise_if_cancelled(cancel)
    ray_dtype, device = c2w.dtype, c2w.device
    background = torch.tensor(settings.background, dtype=ray_dtype, device=device)
    empty = None
    if settings.use_occupancy:
        empty = empty_space if empty_space is not None else empty_space_of(field)
    q_d, q_a = field.param_features(params[None].to(ray_dtype))  # [1, c] each
    dtype = torch.bfloat16 if settings.bf16 and bf16_native(device) else ray_dtype
    frame = FrameField(field, q_d, q_a, dtype)
    step = field.voxel_size() * settings.step_ratio
    out = torch.empty(height * width, 3, dtype=ray_dtype, device=device)
    chunk = rays_per_chunk(settings, device)
    workers = chunk_workers(device) if settings.threaded_chunks else 1
    rows_per_block = max(1, BLOCK_RAYS * batch_factor(device) // width)
    for start in range(0, height, rows_per_block):
        stop = min(height, start + rows_per_block)
        rays_o, rays_d = (r.reshape(-1, 3) for r in image_rays(c2w, intrinsics, (start, stop)))  # [b, 3]
        windows = ray_windows(field, rays_o, rays_d, step, settings.max_samples, empty, cancel=cancel)
        block = out[start * width:stop * width]  # [b, 3], a view

        def march_chunk(i: int, rays_o: Tensor = rays_o, rays_d: Tensor = rays_d, windows: RayWindows = windows,
                        block: Tensor = block) -> None:
            raise_if_cancelled(cancel)
            sl = slice(i * chunk, (i + 1) * chunk)
            block[sl] = march_rays(field, rays_o[sl], rays_d[sl], frame, background, settings, empty, windows[sl])

        map_chunks(march_chunk, math.ceil(rays_o.shape[0] / chunk), workers)
    return out.reshape(height, width, 3)


def render_image_scaled(
    field: VisNerfField,
    c2w: Float[Tensor, "4 4"],
    intrinsics: Intrinsics,
    params: Float[Tensor, " k"],
    settings: RenderSettings,
    empty_space: EmptySpace | None = None,
    cancel: CancelCheck | None = None,
) -> Float[Tensor, "h w 3"]:
    """``render_image`` marched at ``settings.resolution_scale`` of the camera's size and upsampled
    bilinearly to that size (the preview quality); the full size itself when the scale is 1."""
    width, height = intrinsics.width, intrinsics.height
    w_r = max(1, round(width * settings.resolution_scale))
    h_r = max(1, round(height * settings.resolution_scale))
    if (w_r, h_r) == (width, height):
        return render_image(field, c2w, intrinsics, params, settings, empty_space, cancel)
    rgb = render_image(field, c2w, intrinsics.scaled(w_r, h_r), params, settings, empty_space, cancel)  # [h_r, w_r, 3]
    return F.interpolate(rgb.permute(2, 0, 1)[None], size=(height, width), mode="bilinear",
                         align_corners=False)[0].permute(1, 2, 0)


def march_rays(
    field: VisNerfField,
    rays_o: Float[Tensor, "n 3"],
    rays_d: Float[Tensor, "n 3"],
    frame: FrameField,
    background: Float[Tensor, " 3"],
    settings: RenderSettings,
    empty_space: EmptySpace | None,
    windows: RayWindows | None = None,
) -> Float[Tensor, "n 3"]:
    """March rays through their sample windows in segments, testing each sample's cell in
    ``empty_space`` (None: every sample counts) and dropping rays that became opaque or left
    their window. ``windows`` defaults to ``ray_windows`` of these rays."""
    n = rays_o.shape[0]
    step = field.voxel_size() * settings.step_ratio
    if windows is None:
        windows = ray_windows(field, rays_o, rays_d, step, settings.max_samples, empty_space)
    rgbw = torch.zeros(n, 4, dtype=rays_o.dtype, device=rays_o.device)  # weighted colour, shaded weight
    tau_total = torch.zeros(n, dtype=rays_o.dtype, device=rays_o.device)
    active = (windows.first <= windows.last).nonzero()[:, 0]
    if active.numel() == 0:
        return background[None].expand(n, 3).clone()
    # Per active ray, compacted as rays drop out (``index_select``: advanced indexing is several
    # times slower on the CPU).
    first, last = windows.first.index_select(0, active), windows.last.index_select(0, active)
    t_near, t_far = windows.t_near.index_select(0, active), windows.t_far.index_select(0, active)
    origins, directions = rays_o.index_select(0, active), rays_d.index_select(0, active)
    tau_active = torch.zeros(active.shape[0], dtype=rays_o.dtype, device=rays_o.device)
    longest = int((last - first).max()) + 1
    seg_max = settings.segment_samples if settings.early_termination else longest
    seg = min(seg_max, settings.first_segment_samples) if settings.early_termination else longest
    ray_terms = frame.direction_terms(rays_d)  # [n, h], once per ray
    tau_stop = -math.log(settings.early_stop_eps) if settings.early_termination else math.inf
    weight_threshold = settings.weight_threshold_per_voxel * settings.step_ratio  # per sample at this spacing
    all_offsets = torch.arange(seg_max, device=rays_o.device)
    compiled = march_kernel.available(rays_o.device) and rays_o.dtype == torch.float32
    occupancy = None
    if compiled and empty_space is not None:
        occupancy = empty_space.tables(empty_space.occupied).arrays()
    s0 = 0
    while s0 < longest:
        if compiled:  # the same segment in two compiled loops (``rendering.march_kernel``)
            points, flat = march_kernel.place(origins, directions, t_near, t_far, first, last, s0, seg, step, occupancy)
            _shade_placed_samples(frame, ray_terms, active, points, flat, seg, step, tau_active, weight_threshold, rgbw)
            segment_end = first + (s0 + seg - 1)  # [a]
        else:
            idx = (first + s0)[:, None] + all_offsets[None, :seg]  # [a, s]
            t = t_near[:, None] + step * (idx.to(rays_o.dtype) + 0.5)
            valid = (idx <= last[:, None]) & (t < t_far[:, None])
            points = origins[:, None, :] + directions[:, None, :] * t[..., None]  # [a, s, 3]
            if empty_space is not None:
                flat = valid.view(-1).nonzero()[:, 0]
                valid = torch.zeros_like(valid).view(-1).index_copy_(
                    0, flat, empty_space.occupied_at(points.view(-1, 3).index_select(0, flat))).view_as(valid)
            tau_active += _shade_frame_samples(
                frame, ray_terms, active, points, step, valid, tau_active, weight_threshold, rgbw,
            )
            segment_end = idx[:, -1]
        s0 += seg
        seg = min(seg_max, 2 * seg)
        keep = ((tau_active < tau_stop) & (segment_end < last)).nonzero()[:, 0]
        if keep.numel() < active.numel():
            tau_total.index_copy_(0, active, tau_active)
            if keep.numel() == 0:
                active = keep
                break
            active, first, last, t_near, t_far, origins, directions, tau_active = (
                x.index_select(0, keep) for x in (active, first, last, t_near, t_far, origins, directions, tau_active)
            )
    if active.numel() > 0:
        tau_total.index_copy_(0, active, tau_active)
    opacity = -torch.expm1(-tau_total)
    rgb = rgbw[:, :3]
    if weight_threshold > 0.0:
        rgb = rgb * _unshaded_gain(opacity, rgbw[:, 3])[:, None]
    return rgb + background[None] * (1.0 - opacity)[:, None]


def _unshaded_gain(opacity: Float[Tensor, " n"], shaded: Float[Tensor, " n"]) -> Float[Tensor, " n"]:
    """Gain that gives the weight of the samples not shaded (weight at most ``weight_threshold``
    each) the mean colour of the ray's shaded samples instead of black: ``opacity / shaded``.

    The dropped weight ``opacity - shaded`` then costs at most that weight times the spread of the
    colours about their mean, instead of that weight times the colour. The scaled colour is the
    mean colour (each channel in [0, 1]) times ``opacity``, so it stays within [0, opacity] however
    small ``shaded`` is. Rays with no shaded sample keep no colour (gain 1; their opacity is at
    most the dropped weights).
    """
    safe = shaded > 0.0
    return torch.where(safe, opacity / torch.where(safe, shaded, 1.0), 1.0)
