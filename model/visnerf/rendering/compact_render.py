"""The fused training step's render: ``renderer.drop_occluded`` and ``renderer.shade_rays`` on
compact samples (``compact_samples``), through ``TrainingField`` and ``composite_kernel``.

Same samples, same random draws in the same order (the near-empty densities traced,
``density_gradients.traced_samples``; the light samples coloured, ``colour_sampling.draw_coloured``),
same values to float rounding, same gradients (``tests/model/training/test_fused_step.py`` against
the torch path in float64); the work is a handful of compiled loops and the decoders' products.
"""

import math
from typing import no_type_check

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from visnerf import compiled
from visnerf.rendering.colour_sampling import ColourSampling, draw_coloured
from visnerf.rendering.compact_samples import CompactSamples
from visnerf.rendering.composite_kernel import composite, sample_weights
from visnerf.rendering.density_gradients import DensityGradientSampling, traced_samples
from visnerf.rendering.render_settings import RenderSettings
from visnerf.representation.training_field import TrainingField


@no_type_check  # compiled by numba
def _segment(offsets, active, reached, seg, out):
    """The samples ``reached[a] .. reached[a] + seg - 1`` of each active ray ``active[a]`` (within
    its own), into ``out``; returns their count."""
    m = 0
    for a in range(active.shape[0]):
        r = active[a]
        stop = min(offsets[r] + reached[a] + seg, offsets[r + 1])
        for i in range(offsets[r] + reached[a], stop):
            out[m] = i
            m += 1
    return m


@no_type_check
def _advance(offsets, active, reached, seg, sigma, step, depth, depth_stop, seen, sigma_out, n_active):
    """Composite a segment (``sigma`` in ``_segment``'s order): each sample seen where the optical
    depth before it is below ``depth_stop``, its density kept; the rays left to march moved to the
    front of ``active`` (``reached`` and ``depth`` with them); returns their count."""
    j = 0
    kept = 0
    for a in range(n_active):
        r = active[a]
        start = offsets[r] + reached[a]
        stop = min(start + seg, offsets[r + 1])
        d = depth[a]
        for i in range(start, stop):
            if d < depth_stop:
                seen[i] = True
                sigma_out[i] = sigma[j]
            d += float(sigma[j]) * step
            j += 1
        if d < depth_stop and stop < offsets[r + 1]:
            active[kept] = r
            reached[kept] = stop - offsets[r]
            depth[kept] = d
            kept += 1
    return kept


_segment_loop = compiled.jit(_segment)
_advance_loop = compiled.jit(_advance)


@torch.no_grad()
def drop_occluded_compact(
    tfield: TrainingField,
    samples: CompactSamples,
    params: Float[Tensor, "n k"],
    step: float,
    stop_eps: float,
    first_segment: int = RenderSettings.first_segment_samples,
) -> CompactSamples:
    """``renderer.drop_occluded`` on compact samples: those a ray reaches with transmittance at or
    above ``stop_eps``, with their densities. A sample is kept exactly when the optical depth
    before it is below ``-log(stop_eps)``, whatever the segments the rays are marched in, so the
    kept samples are the torch path's. ``stop_eps`` 0 returns ``samples`` as they are."""
    if stop_eps <= 0.0 or len(samples) == 0:
        return samples
    q_d, _ = tfield.param_features(params)
    offsets = samples.offsets.numpy()
    counts = samples.per_ray()
    active = (counts > 0).nonzero()[:, 0].numpy().astype(np.int64)
    reached = np.zeros(active.shape[0], np.int64)
    depth = np.zeros(active.shape[0], np.float64)
    seen = np.zeros(len(samples), np.bool_)
    sigma_out = torch.zeros(len(samples), dtype=samples.points.dtype)
    index = np.empty(len(samples), np.int64)
    depth_stop = -math.log(stop_eps)
    n_active, seg = active.shape[0], first_segment
    while n_active > 0:
        m = _segment_loop(offsets, active[:n_active], reached, seg, index)
        picked = torch.from_numpy(index[:m])
        sigma = tfield.density(samples.points.index_select(0, picked), samples.ray.index_select(0, picked), q_d)
        n_active = _advance_loop(offsets, active, reached, seg, sigma.numpy(), float(step), depth, depth_stop, seen,
                                 sigma_out.numpy(), n_active)
        seg *= 2
    return samples.keep(torch.from_numpy(seen), sigma_out)


def shade_compact(
    tfield: TrainingField,
    rays_d: Float[Tensor, "n 3"],
    params: Float[Tensor, "n k"],
    background: Float[Tensor, "n 3"],
    samples: CompactSamples,
    step: float,
    weight_threshold: float = 1e-4,
    density_grads: DensityGradientSampling | None = None,
    colour_sampling: ColourSampling | None = None,
) -> dict[str, Tensor]:
    """``renderer.shade_rays`` on compact samples: ``rgb`` [n, 3], ``opacity`` [n], ``n_samples``."""
    q_d, q_a = tfield.param_features(params)
    points, ray = samples.points, samples.ray
    trace_all = density_grads is None or density_grads.keep == 1.0 or not torch.is_grad_enabled()
    if trace_all:
        traced_sigma = tfield.density(points, ray, q_d)
        sigma = traced_sigma.detach()
        traced = torch.arange(len(samples))
        traced_gain = torch.ones(len(samples), dtype=sigma.dtype)
    elif samples.sigma is not None:  # densities known (occluded samples dropped): trace some again
        sigma = samples.sigma
        traced, traced_gain = traced_samples(sigma, step, density_grads)
        traced_sigma = tfield.density(points.index_select(0, traced), ray.index_select(0, traced), q_d)
    else:  # every density once without a graph, the traced ones made differentiable from the same rows
        sigma, taken = tfield.density_taken(points, ray, q_d)
        traced, traced_gain = traced_samples(sigma, step, density_grads)
        traced_sigma = tfield.density_of_taken(taken, traced, q_d)
    weights = sample_weights(samples.offsets, sigma, step)
    candidates = (weights > weight_threshold).nonzero()[:, 0]
    shade, gain = draw_coloured(weights, candidates, colour_sampling)
    colour = tfield.color(points.index_select(0, shade), ray.index_select(0, shade), q_a,
                          tfield.direction_terms(rays_d), rays_d, q_d)
    rgb, depth = composite(traced_sigma, colour, sigma, traced, traced_gain.to(sigma.dtype), samples.offsets, step,
                           shade, gain.to(sigma.dtype), background.to(colour.dtype))
    return {"rgb": rgb, "opacity": -torch.expm1(-depth).to(rgb.dtype), "n_samples": torch.tensor(len(samples))}
