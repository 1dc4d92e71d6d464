"""Sample placement along rays: uniform steps with per-ray jitter."""

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
