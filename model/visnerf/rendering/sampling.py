"""Sample placement along rays: uniform steps and importance sampling from a coarse pass."""

import torch
from jaxtyping import Float
from torch import Tensor


def uniform_noise(
    shape: tuple[int, ...], generator: torch.Generator, device: torch.device, dtype: torch.dtype = torch.float32
) -> Tensor:
    """U[0, 1) of ``shape`` on ``device``, drawn where ``generator`` lives (the trainer's is a CPU
    generator, also when it trains on CUDA): a seed gives the same samples on every device."""
    return torch.rand(shape, generator=generator, device=generator.device, dtype=dtype).to(device)


def uniform_samples(
    t_near: Float[Tensor, " n"],
    n_samples: int,
    step: float,
    jitter: Float[Tensor, " n"] | None = None,
) -> Float[Tensor, "n s"]:
    """Sample centres ``t_near + step * (i + u)``; ``u`` is 0.5 (deterministic) or per-ray jitter."""
    offsets = torch.arange(n_samples, device=t_near.device, dtype=t_near.dtype)  # [s]
    u = torch.full_like(t_near, 0.5) if jitter is None else jitter
    return t_near[:, None] + step * (offsets[None, :] + u[:, None])


def sample_pdf(
    bins: Float[Tensor, "n b1"],
    weights: Float[Tensor, "n b"],
    n_samples: int,
    generator: torch.Generator | None = None,
    eps: float = 1e-5,
) -> Float[Tensor, "n s"]:
    """Inverse-CDF samples from a piecewise-constant pdf over the intervals ``bins``.

    ``bins`` holds interval edges ``[n, b + 1]``; ``weights`` the mass of each interval. A ray with
    no mass samples uniformly. Stratified in training (``generator`` given), centred otherwise.
    Returns sorted positions. Not differentiable in ``weights``.
    """
    n, b = weights.shape
    w = weights.detach() + eps
    pdf = w / w.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros(n, 1, dtype=pdf.dtype, device=pdf.device), torch.cumsum(pdf, -1)], -1)
    cdf = cdf.clamp(max=1.0)  # [n, b + 1]
    base = (torch.arange(n_samples, device=w.device, dtype=w.dtype) + 0.5) / n_samples
    if generator is not None:
        jitter = (uniform_noise((n, n_samples), generator, w.device, w.dtype) - 0.5) / n_samples
        u = (base[None] + jitter).clamp(0.0, 1.0 - 1e-6)
    else:
        u = base.expand(n, n_samples).contiguous()
    idx = torch.searchsorted(cdf, u, right=True).clamp(1, b)  # [n, s]
    c0, c1 = cdf.gather(1, idx - 1), cdf.gather(1, idx)
    b0, b1 = bins.gather(1, idx - 1), bins.gather(1, idx)
    frac = ((u - c0) / (c1 - c0).clamp_min(torch.finfo(w.dtype).eps)).clamp(0.0, 1.0)
    return torch.sort(b0 + frac * (b1 - b0), dim=-1).values


def deltas_from_samples(t: Float[Tensor, "n s"], t_far: Float[Tensor, " n"]) -> Float[Tensor, "n s"]:
    """Interval lengths for sorted, non-uniform samples: distance to the next sample, the last to ``t_far``."""
    nxt = torch.cat([t[:, 1:], t_far[:, None].expand(-1, 1)], dim=-1)
    return (nxt - t).clamp_min(0.0)
