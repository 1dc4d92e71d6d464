"""Compositing of a training batch's compact samples, forward and backward, as compiled loops (CPU, numba).

A training step's samples are compact: ray ``r`` owns samples ``offsets[r] .. offsets[r + 1] - 1``
in front-to-back order, all ``step`` apart. The colour ``C_r = sum_i g_i w_i c_i + b_r T_r`` sums
the shaded samples (``shade``, increasing indices; ``g_i`` a gain, 1 unless colour sampling drew
the sample), with ``w_i = exp(-S_i) (1 - exp(-tau_i))``, ``tau_i = sigma_i * step``, ``S_i`` the
optical depth before sample ``i`` (log-space transmittance, as ``rendering.volume``) and ``T_r``
the ray's final transmittance.

Its gradient, for ``a_i = g_i c_i . dC`` (0 for a sample not shaded):
``dtau_j = a_j exp(-S_j - tau_j) - sum_{i > j} a_i w_i - (b . dC) T_r``, a suffix sum over the
ray; ``dc_i = g_i w_i dC``. Optical depths are summed in float64 whatever the samples' type.
``tests/model/rendering/test_composite_kernel.py`` checks both against autograd through
``rendering.volume`` in float64.
"""

import math
from typing import no_type_check

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor

from visnerf import compiled


@no_type_check  # compiled by numba
def _weights(offsets, sigma, step, out):
    """``out[i] = w_i`` of every sample."""
    for r in range(offsets.shape[0] - 1):
        before = 0.0
        for i in range(offsets[r], offsets[r + 1]):
            tau = float(sigma[i]) * step
            out[i] = math.exp(-before) * -math.expm1(-tau)
            before += tau


@no_type_check
def _forward(offsets, sigma, step, shade, colour, gain, background, out_rgb, out_depth):
    """``out_rgb[r] = C_r`` and ``out_depth[r] = -log T_r``."""
    j = 0
    k = shade.shape[0]
    for r in range(offsets.shape[0] - 1):
        before = 0.0
        acc0 = acc1 = acc2 = 0.0
        for i in range(offsets[r], offsets[r + 1]):
            tau = float(sigma[i]) * step
            if j < k and shade[j] == i:
                w = math.exp(-before) * -math.expm1(-tau) * float(gain[j])
                acc0 += w * float(colour[j, 0])
                acc1 += w * float(colour[j, 1])
                acc2 += w * float(colour[j, 2])
                j += 1
            before += tau
        t = math.exp(-before)
        out_rgb[r, 0] = acc0 + float(background[r, 0]) * t
        out_rgb[r, 1] = acc1 + float(background[r, 1]) * t
        out_rgb[r, 2] = acc2 + float(background[r, 2]) * t
        out_depth[r] = before


@no_type_check
def _backward(offsets, sigma, step, shade, colour, gain, background, grad_rgb, grad_sigma, grad_colour):
    """``grad_sigma[i] = dL/dsigma_i`` of every sample and ``grad_colour[j] = dL/dc`` of every
    shaded one, from ``grad_rgb[r] = dL/dC_r``."""
    k = shade.shape[0]
    j_end = 0
    for r in range(offsets.shape[0] - 1):
        start, stop = offsets[r], offsets[r + 1]
        g0, g1, g2 = float(grad_rgb[r, 0]), float(grad_rgb[r, 1]), float(grad_rgb[r, 2])
        j_start = j_end
        total = 0.0
        for i in range(start, stop):
            total += float(sigma[i]) * step
            if j_end < k and shade[j_end] == i:
                j_end += 1
        bg_term = (float(background[r, 0]) * g0 + float(background[r, 1]) * g1
                   + float(background[r, 2]) * g2) * math.exp(-total)
        after = 0.0  # sum of a_i w_i over the later samples
        j = j_end - 1
        through = total  # S_i + tau_i of sample i, walking back
        for i in range(stop - 1, start - 1, -1):
            tau = float(sigma[i]) * step
            before = through - tau
            dtau = -after - bg_term
            if j >= j_start and shade[j] == i:
                w = math.exp(-before) * -math.expm1(-tau)
                gw = w * float(gain[j])
                a = float(gain[j]) * (float(colour[j, 0]) * g0 + float(colour[j, 1]) * g1 + float(colour[j, 2]) * g2)
                dtau += a * math.exp(-through)
                after += a * w
                grad_colour[j, 0] = gw * g0
                grad_colour[j, 1] = gw * g1
                grad_colour[j, 2] = gw * g2
                j -= 1
            grad_sigma[i] = dtau * step
            through = before


_weights_loop = compiled.jit(_weights)
_forward_loop = compiled.jit(_forward)
_backward_loop = compiled.jit(_backward)


def available(device: torch.device) -> bool:
    """Whether the compiled loops serve ``device`` (``compiled.serves``)."""
    return compiled.serves(device)


def _np(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


def sample_weights(offsets: Int[Tensor, " n1"], sigma: Float[Tensor, " m"], step: float) -> Float[Tensor, " m"]:
    """Compositing weights of every sample (no gradient)."""
    out = torch.empty_like(sigma)
    _weights_loop(_np(offsets), _np(sigma), float(step), out.numpy())
    return out


class _Composite(torch.autograd.Function):
    """``C_r`` of the module docstring, differentiable in the traced densities and the colours."""

    @staticmethod
    def forward(ctx, traced_sigma, colour, sigma, traced, traced_gain, offsets, step, shade, gain, background):
        n = offsets.shape[0] - 1
        rgb = torch.empty(n, 3, dtype=colour.dtype)
        depth = torch.empty(n, dtype=torch.float64)
        arrays = [_np(t) for t in (offsets, sigma, shade, colour, gain, background)]
        _forward_loop(arrays[0], arrays[1], float(step), *arrays[2:], rgb.numpy(), depth.numpy())
        ctx.save_for_backward(offsets, sigma, shade, colour, gain, background, traced, traced_gain)
        ctx.step = float(step)
        ctx.mark_non_differentiable(depth)
        return rgb, depth

    @staticmethod
    def backward(ctx, grad_rgb, _grad_depth):
        offsets, sigma, shade, colour, gain, background, traced, traced_gain = ctx.saved_tensors
        grad_sigma = torch.zeros_like(sigma)
        grad_colour = torch.zeros_like(colour)
        _backward_loop(_np(offsets), _np(sigma), ctx.step, _np(shade), _np(colour), _np(gain), _np(background),
                       _np(grad_rgb), grad_sigma.numpy(), grad_colour.numpy())
        grad_traced = grad_sigma.index_select(0, traced) * traced_gain
        return grad_traced, grad_colour, None, None, None, None, None, None, None, None


def composite(
    traced_sigma: Float[Tensor, " t"],
    colour: Float[Tensor, "k 3"],
    sigma: Float[Tensor, " m"],
    traced: Int[Tensor, " t"],
    traced_gain: Float[Tensor, " t"],
    offsets: Int[Tensor, " n1"],
    step: float,
    shade: Int[Tensor, " k"],
    gain: Float[Tensor, " k"],
    background: Float[Tensor, "n 3"],
) -> tuple[Float[Tensor, "n 3"], Float[Tensor, " n"]]:
    """(colour of each ray, its optical depth ``-log T_r`` in float64) from the densities
    ``sigma`` of every sample and the colours of the ``shade`` samples. Differentiable in
    ``colour`` and in ``traced_sigma``, the densities of samples ``traced`` (their values are
    ``sigma[traced]``), whose gradient is the densities' times ``traced_gain``; the other
    densities carry none (``rendering.density_gradients``)."""
    return _Composite.apply(traced_sigma, colour, sigma.detach(), traced, traced_gain, offsets, step, shade, gain,
                            background)
