"""Frames: rays in, colours out (inference; the training path is ``training_render``).

``render_image``: deterministic samples on a lattice
one step apart; each ray walks only the window between its first and last sample in an occupied
cell (found by jumping over empty blocks, ``rendering.empty_space``), in segments, testing each
sample's cell, until it leaves the window or its transmittance falls below ``early_stop_eps``.
Chunks of rays are marched on one thread per core (``rendering.parallel``). On the CPU the walk,
each segment's placing and compositing, and the decoders' input rows are compiled loops
(``empty_space_kernel``, ``march_kernel``, ``representation.vm_kernel``); other devices run the
same steps as torch operations.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float, Int
from torch import Tensor

from visnerf.data.cameras import Intrinsics, image_rays, rays_from_pixels
from visnerf.rendering import march_kernel
from visnerf.rendering.cancel import CancelCheck, raise_if_cancelled
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.parallel import chunk_workers, map_chunks
from visnerf.rendering.ray_windows import RayWindows, empty_space_of, ray_windows
from visnerf.rendering.refine import refine_frame, refinement_spacing
from visnerf.rendering.render_settings import RenderSettings, rays_per_chunk
from visnerf.rendering.volume import weights_from_optical_depth
from visnerf.representation.field import VisNerfField
from visnerf.representation.frame_field import FrameField, SampleTaps
from visnerf.runtime import batch_factor, bf16_native

BLOCK_RAYS = 262144
"""Rays of a frame made, walked and marched at a time (``render_image``), 512x512 pixels: the
empty-space walk runs on all of a block's rays at once, so blocks bound a large frame's peak
memory at the same speed; a frame of at most this many rays is one block
(docs/decisions.md#frames.blocks)."""


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
    _add_shaded_colours(frame, ray_terms, rays, samples, flat, s, valid_weights, shade, rgbw, compiled=False)
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
    compiled: bool,
) -> None:
    """Add the weighted colour and the weight of samples ``shade`` (indices into the segment's
    valid ``samples``, whose flat indices are ``flat``: ``ray * seg + j``) into ``rgbw``;
    ``compiled``: by ``march_kernel.accumulate`` (the frame's march chose the compiled loops)."""
    if shade.numel() == 0:
        return
    ray_idx = rays.index_select(0, flat.index_select(0, shade) // seg)
    colors = frame.color_at(samples.select(shade), ray_terms.index_select(0, ray_idx))  # [k, 3]
    if compiled:
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
    _add_shaded_colours(frame, ray_terms, rays, samples, flat, seg, weights, shade, rgbw, compiled=True)


@dataclass(frozen=True)
class _FrameMarch:
    """What every ray of one frame is marched with: the frame's field at its parameters, the
    sample spacing, the background, the occupancy and the chunks."""

    field: VisNerfField
    frame: FrameField
    background: Float[Tensor, " 3"]
    settings: RenderSettings
    empty: EmptySpace | None
    step: float
    chunk: int
    workers: int
    cancel: CancelCheck | None

    def march(self, rays_o: Float[Tensor, "b 3"], rays_d: Float[Tensor, "b 3"], out: Float[Tensor, "b 3"]) -> None:
        """March a block of rays, chunk by chunk on the frame's threads, into ``out``; each chunk
        walks its own rays' windows, so the walk is shared by the threads as the march is."""

        def march_chunk(i: int) -> None:
            raise_if_cancelled(self.cancel)
            sl = slice(i * self.chunk, (i + 1) * self.chunk)
            windows = ray_windows(self.field, rays_o[sl], rays_d[sl], self.step, self.settings.max_samples, self.empty,
                                  cancel=self.cancel)
            out[sl] = march_rays(self.field, rays_o[sl], rays_d[sl], self.frame, self.background, self.settings,
                                 self.empty, windows)

        map_chunks(march_chunk, math.ceil(rays_o.shape[0] / self.chunk), self.workers)


def _frame_march(field: VisNerfField, c2w: Tensor, params: Float[Tensor, " k"], settings: RenderSettings,
                 empty_space: EmptySpace | None, cancel: CancelCheck | None) -> _FrameMarch:
    ray_dtype, device = c2w.dtype, c2w.device
    background = torch.tensor(settings.background, dtype=ray_dtype, device=device)
    empty = None
    if settings.use_occupancy:
        empty = empty_space if empty_space is not None else empty_space_of(field)
    q_d, q_a = field.param_features(params[None].to(ray_dtype))  # [1, c] each
    dtype = torch.bfloat16 if settings.bf16 and bf16_native(device) else ray_dtype
    return _FrameMarch(field, FrameField(field, q_d, q_a, dtype), background, settings, empty,
                       field.voxel_size() * settings.step_ratio, rays_per_chunk(settings, device),
                       chunk_workers(device), cancel)


def render_image(
    field: VisNerfField,
    c2w: Float[Tensor, "4 4"],
    intrinsics: Intrinsics,
    params: Float[Tensor, " k"],
    settings: RenderSettings,
    empty_space: EmptySpace | None = None,
    cancel: CancelCheck | None = None,
) -> Float[Tensor, "h w 3"]:
    """Render one image at normalised parameters (inference; call under ``torch.inference_mode``),
    every pixel marched.

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
    marcher = _frame_march(field, c2w, params, settings, empty_space, cancel)
    out = torch.empty(height * width, 3, dtype=c2w.dtype, device=c2w.device)
    rows_per_block = max(1, BLOCK_RAYS * batch_factor(c2w.device) // width)
    for start in range(0, height, rows_per_block):
        stop = min(height, start + rows_per_block)
        rays_o, rays_d = (r.reshape(-1, 3) for r in image_rays(c2w, intrinsics, (start, stop)))  # [b, 3]
        marcher.march(rays_o, rays_d, out[start * width:stop * width])
    return out.reshape(height, width, 3)


def render_pixels(
    field: VisNerfField,
    c2w: Float[Tensor, "4 4"],
    intrinsics: Intrinsics,
    params: Float[Tensor, " k"],
    settings: RenderSettings,
    empty_space: EmptySpace | None = None,
    cancel: CancelCheck | None = None,
) -> Callable[[Int[Tensor, " n"], Int[Tensor, " n"]], Float[Tensor, "n 3"]]:
    """A function that marches the pixels at columns ``u`` and rows ``v`` of the frame
    ``render_image`` would make (the same rays; in blocks of ``BLOCK_RAYS``)."""
    marcher = _frame_march(field, c2w, params, settings, empty_space, cancel)
    block = BLOCK_RAYS * batch_factor(c2w.device)

    def render(u: Int[Tensor, " n"], v: Int[Tensor, " n"]) -> Float[Tensor, "n 3"]:
        out = torch.empty(u.shape[0], 3, dtype=c2w.dtype, device=c2w.device)
        for start in range(0, u.shape[0], block):
            sl = slice(start, start + block)
            uu, vv = (x[sl].to(c2w.dtype) + 0.5 for x in (u, v))
            rays_o, rays_d = rays_from_pixels(c2w.expand(uu.shape[0], 4, 4), intrinsics, uu, vv)
            marcher.march(rays_o, rays_d, out[sl])
        return out

    return render


def render_image_scaled(
    field: VisNerfField,
    c2w: Float[Tensor, "4 4"],
    intrinsics: Intrinsics,
    params: Float[Tensor, " k"],
    settings: RenderSettings,
    empty_space: EmptySpace | None = None,
    cancel: CancelCheck | None = None,
) -> Float[Tensor, "h w 3"]:
    """The frame as the server shows it: with ``settings.resolution_scale`` below 1 (the preview)
    ``render_image`` at that scale, upsampled bilinearly; at full scale, where a voxel spans two
    pixels or more (``refine.refinement_spacing``, at most ``settings.refine_spacing``), a lattice
    of pixels and the cells whose corners differ by more than ``settings.refine_spread``
    (``refine.refine_frame``); else every pixel."""
    width, height = intrinsics.width, intrinsics.height
    w_r = max(1, round(width * settings.resolution_scale))
    h_r = max(1, round(height * settings.resolution_scale))
    if (w_r, h_r) == (width, height):
        spacing = 1
        if settings.refine_spacing > 1:
            spacing = refinement_spacing(field.aabb, field.voxel_size(), c2w, intrinsics, settings.refine_spacing)
        if spacing <= 1:
            return render_image(field, c2w, intrinsics, params, settings, empty_space, cancel)
        raise_if_cancelled(cancel)
        render = render_pixels(field, c2w, intrinsics, params, settings, empty_space, cancel)
        return refine_frame(render, height, width, spacing, settings.refine_spread, c2w.device, c2w.dtype)
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
    first, last, t_near, t_far, origins, directions = (
        x.index_select(0, active) for x in (windows.first, windows.last, windows.t_near, windows.t_far, rays_o, rays_d))
    tau_active = torch.zeros(active.shape[0], dtype=rays_o.dtype, device=rays_o.device)
    longest = int((last - first).max()) + 1
    seg_max = settings.segment_samples if settings.early_termination else longest
    seg = min(seg_max, settings.first_segment_samples) if settings.early_termination else longest
    ray_terms = frame.direction_terms(rays_d)  # [n, h], once per ray
    tau_stop = -math.log(settings.early_stop_eps) if settings.early_termination else math.inf
    weight_threshold = settings.weight_threshold_per_voxel * settings.step_ratio  # per sample at this spacing
    compiled = march_kernel.available(rays_o.device) and rays_o.dtype == torch.float32
    occupancy = empty_space.tables(empty_space.occupied).arrays() if compiled and empty_space is not None else None
    s0 = 0
    while s0 < longest and active.numel() > 0:
        if compiled:  # the same segment in two compiled loops (``rendering.march_kernel``)
            points, flat = march_kernel.place(origins, directions, t_near, t_far, first, last, s0, seg, step, occupancy)
            _shade_placed_samples(frame, ray_terms, active, points, flat, seg, step, tau_active, weight_threshold, rgbw)
            segment_end = first + (s0 + seg - 1)  # [a]
        else:
            idx = (first + s0)[:, None] + torch.arange(seg, device=first.device)[None, :]  # [a, s]
            points, valid = _segment_samples(idx, last, t_near, t_far, origins, directions, step, empty_space)
            tau_active += _shade_frame_samples(frame, ray_terms, active, points, step, valid, tau_active,
                                               weight_threshold, rgbw)
            segment_end = idx[:, -1]
        s0 += seg
        seg = min(seg_max, 2 * seg)
        keep = ((tau_active < tau_stop) & (segment_end < last)).nonzero()[:, 0]
        if keep.numel() < active.numel():
            tau_total.index_copy_(0, active, tau_active)
            active, first, last, t_near, t_far, origins, directions, tau_active = (
                x.index_select(0, keep) for x in (active, first, last, t_near, t_far, origins, directions, tau_active)
            )
    if active.numel() > 0:
        tau_total.index_copy_(0, active, tau_active)
    return _over_background(rgbw, tau_total, background, weight_threshold)


def _segment_samples(
    idx: Int[Tensor, "a s"], last: Int[Tensor, " a"], t_near: Float[Tensor, " a"],
    t_far: Float[Tensor, " a"], origins: Float[Tensor, "a 3"], directions: Float[Tensor, "a 3"], step: float,
    empty_space: EmptySpace | None,
) -> tuple[Float[Tensor, "a s 3"], Bool[Tensor, "a s"]]:
    """The torch twin of ``march_kernel.place``: a segment's sample points and which of them count
    (inside the ray's window and, with ``empty_space``, in an occupied cell)."""
    t = t_near[:, None] + step * (idx.to(origins.dtype) + 0.5)
    valid = (idx <= last[:, None]) & (t < t_far[:, None])
    points = origins[:, None, :] + directions[:, None, :] * t[..., None]
    if empty_space is not None:
        flat = valid.view(-1).nonzero()[:, 0]
        valid = torch.zeros_like(valid).view(-1).index_copy_(
            0, flat, empty_space.occupied_at(points.view(-1, 3).index_select(0, flat))).view_as(valid)
    return points, valid


def _over_background(
    rgbw: Float[Tensor, "n 4"], tau: Float[Tensor, " n"], background: Float[Tensor, " 3"], weight_threshold: float,
) -> Float[Tensor, "n 3"]:
    """Marched colour over the background: opacity ``1 - exp(-tau)``; the weight of samples skipped
    under ``weight_threshold`` given back to the shaded ones (``_unshaded_gain``)."""
    opacity = -torch.expm1(-tau)
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
