"""Densities for training whose backward pass skips most near-empty samples, without bias.

Most samples a training step evaluates lie in occupied cells yet hold almost nothing (the occupancy
grid is the union over all parameter settings, dilated by a cell;
docs/decisions.md#step.sampled_density_gradients). Their gradient is small as well: the density is
``softplus(raw)``, whose slope ``1 - exp(-sigma)`` is about ``sigma`` near zero, and the loss sees
a sample through ``sigma * delta``. Back-propagating them still costs as much per sample as any
other, and the density backward was the largest part of a step.

``density_with_sampled_gradients`` evaluates every sample's density without a graph, then again,
differentiably, for the samples whose alpha reaches ``floor`` and for a random fraction ``keep`` of
the others, whose gradient it scales by ``1 / keep``. Every value is the density itself; the
gradient is an unbiased estimate of the full one (each near-empty sample's gradient counts
``1 / keep`` times with probability ``keep``); samples at or above the floor are exact.
"""

from collections.abc import Callable
from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from torch import Tensor

from visnerf.rendering.sampling import uniform_noise

DensityFn = Callable[[Float[Tensor, "m 3"], Float[Tensor, "m d"]], Float[Tensor, " m"]]


@dataclass(frozen=True)
class DensityGradientSampling:
    """Which samples' densities the backward pass takes: those with alpha at least ``floor`` and
    a ``keep`` fraction of the rest, in (0, 1], drawn from ``generator``."""

    floor: float
    keep: float
    generator: torch.Generator

    def __post_init__(self) -> None:
        if not 0.0 < self.keep <= 1.0:
            raise ValueError(f"keep must be in (0, 1], got {self.keep}")


def traced_samples(
    sigma: Float[Tensor, " m"], deltas: Float[Tensor, " m"] | float, sampling: DensityGradientSampling
) -> tuple[Int[Tensor, " k"], Float[Tensor, " k"]]:
    """The samples whose densities a step back-propagates, and the factor on each one's gradient:
    every sample with ``1 - exp(-sigma * delta) >= sampling.floor`` (factor 1) and a random
    ``sampling.keep`` fraction of the rest (factor ``1 / keep``). No gradient."""
    with torch.no_grad():
        low = -torch.expm1(-sigma * deltas) < sampling.floor
        drawn = uniform_noise(tuple(sigma.shape), sampling.generator, sigma.device) < sampling.keep
        traced = (~low | drawn).nonzero()[:, 0]  # [k]
        gain = torch.where(low.index_select(0, traced), 1.0 / sampling.keep, 1.0).to(sigma.dtype)
    return traced, gain


def density_with_sampled_gradients(
    density: DensityFn,
    points: Float[Tensor, "m 3"],
    q_density: Float[Tensor, "m d"],
    deltas: Float[Tensor, " m"],
    sampling: DensityGradientSampling,
    known: Float[Tensor, " m"] | None = None,
) -> Float[Tensor, " m"]:
    """``density(points, q_density)`` in value; differentiable through the samples
    ``traced_samples`` picks, scaled by its factors. A keep of 1 back-propagates every sample (the
    plain call). ``known``: the same densities computed earlier without a graph, which saves that
    pass."""
    if sampling.keep == 1.0 or not torch.is_grad_enabled():
        return density(points, q_density)
    with torch.no_grad():
        sigma = density(points, q_density) if known is None else known  # [m]
    traced, gain = traced_samples(sigma, deltas, sampling)
    if traced.numel() == 0:
        return sigma
    exact = density(points.index_select(0, traced), q_density.index_select(0, traced))  # [k]
    # Value ``exact`` (the added term is exactly zero), gradient ``gain`` times its own.
    scaled = exact + (exact - exact.detach()) * (gain.to(exact.dtype) - 1.0)
    return sigma.index_copy(0, traced, scaled)
