"""Narrow peaks of the raw density: a learnt transfer function, so thin shells are level sets.

A transfer function with narrow peaks turns a smooth scalar ``s`` into shells a fraction of a voxel
thick where ``s`` crosses each peak's value. With ``k`` peaks the density decoder's output ``r``
plays ``s``: density = ``scale * (softplus(r + shift) + sum_k h_k exp(-(r - c_k)^2 / 2 w_k^2))``
with centres ``c_k``, widths ``w_k`` and heights ``h_k`` learnt. A trilinear ``r`` crosses ``c_k``
on a plane within a voxel, so a shell's rim is as sharp as ``w_k / |grad r|`` makes it.
"""

import math

import torch
from jaxtyping import Float
from torch import Tensor, nn

FIRST_CENTRE, LAST_CENTRE = 1.0, 3.0
"""Raw values of the first and last peaks at the start: above a fresh field's output (about 0), so
a fresh field is the same faint fog."""
START_WIDTH = 0.25
"""Each peak's width at the start, in raw units."""


class DensityPeaks(nn.Module):
    """``k`` Gaussian peaks of the raw density. Parameters: ``centre``, ``log_width``,
    ``log_height`` [k]."""

    def __init__(self, k: int) -> None:
        super().__init__()
        self.centre = nn.Parameter(torch.linspace(FIRST_CENTRE, LAST_CENTRE, k))
        self.log_width = nn.Parameter(torch.full((k,), math.log(START_WIDTH)))
        self.log_height = nn.Parameter(torch.zeros(k))

    def forward(self, raw: Float[Tensor, " m"]) -> Float[Tensor, " m"]:
        """``sum_k h_k exp(-(raw - c_k)^2 / 2 w_k^2)`` (float32, >= 0)."""
        z = (raw.float()[:, None] - self.centre) * torch.exp(-self.log_width)  # [m, k]
        return (torch.exp(self.log_height - 0.5 * z * z)).sum(-1)
