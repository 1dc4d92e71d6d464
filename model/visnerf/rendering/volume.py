"""Emission-absorption compositing: pure functions, one physical step each.

Layout: padded samples ``[n_rays, n_samples]`` in front-to-back order; an unused sample has
density 0 and contributes nothing. Transmittance is accumulated in log space,
``T_i = exp(-sum_{j<i} sigma_j delta_j)``; alpha is ``-expm1(-sigma delta)``. All functions are
differentiable and keep the input dtype and device.
"""

import torch
from jaxtyping import Float
from torch import Tensor


def optical_depths(
    sigmas: Float[Tensor, "n s"], deltas: Float[Tensor, "n s"]
) -> Float[Tensor, "n s"]:
    """``sigma * delta`` with negative lengths clamped to zero."""
    return sigmas * deltas.clamp_min(0.0)


def render_alpha_from_density(
    sigmas: Float[Tensor, "n s"], deltas: Float[Tensor, "n s"]
) -> Float[Tensor, "n s"]:
    """Opacity of each interval, ``1 - exp(-sigma delta)``, computed as ``-expm1``."""
    return -torch.expm1(-optical_depths(sigmas, deltas))


def exclusive_optical_depth(tau: Float[Tensor, "n s"]) -> Float[Tensor, "n s"]:
    """Optical depth before each sample, ``sum(tau[:, :i])``, as a shifted cumulative sum: a zero,
    then the running sum without the last term. ``cumsum(tau) - tau`` cancels in float32 where a
    large term follows small ones (tau = [0.3, 1e7, 0.5] gave weights summing to 1.26); this never
    subtracts, so it is exact to rounding, and monotone."""
    return torch.cat([torch.zeros_like(tau[:, :1]), torch.cumsum(tau[:, :-1], dim=-1)], dim=-1)


def weights_from_optical_depth(
    tau: Float[Tensor, "n s"], tau_before: Float[Tensor, " n"] | None = None
) -> Float[Tensor, "n s"]:
    """Compositing weights ``T_i * alpha_i`` of a segment of samples with optical depths ``tau``,
    after ``tau_before`` accumulated by the ray's earlier segments (the renderers march in segments)."""
    before = exclusive_optical_depth(tau)
    if tau_before is not None:
        before = before + tau_before[:, None]
    return torch.exp(-before) * -torch.expm1(-tau)


def render_transmittance_from_density(
    sigmas: Float[Tensor, "n s"], deltas: Float[Tensor, "n s"]
) -> Float[Tensor, "n s"]:
    """Transmittance before each sample: ``exp(-exclusive_cumsum(sigma delta))``."""
    return torch.exp(-exclusive_optical_depth(optical_depths(sigmas, deltas)))


def render_weight_from_density(
    sigmas: Float[Tensor, "n s"], deltas: Float[Tensor, "n s"]
) -> tuple[Float[Tensor, "n s"], Float[Tensor, "n s"], Float[Tensor, "n s"]]:
    """(weights, transmittance, alphas) with ``weights = T * alpha``; ``sum(w) = 1 - T_final``."""
    alphas = render_alpha_from_density(sigmas, deltas)
    trans = render_transmittance_from_density(sigmas, deltas)
    return trans * alphas, trans, alphas


def accumulate_along_rays(
    weights: Float[Tensor, "n s"], values: Float[Tensor, "n s c"]
) -> Float[Tensor, "n c"]:
    """``sum_i w_i v_i`` per ray."""
    return torch.einsum("ns,nsc->nc", weights, values)


def composite_background(
    rgb: Float[Tensor, "n 3"], opacity: Float[Tensor, " n"], background: Float[Tensor, "n 3"] | Float[Tensor, " 3"]
) -> Float[Tensor, "n 3"]:
    """``rgb + bg * (1 - opacity)``."""
    return rgb + background * (1.0 - opacity).unsqueeze(-1)
