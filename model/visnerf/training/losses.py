"""Photometric loss."""

import torch
from jaxtyping import Float
from torch import Tensor


def photometric_mse(pred: Float[Tensor, "n 3"], target: Float[Tensor, "n 3"]) -> Tensor:
    """Mean squared error over rays and channels."""
    return torch.mean((pred - target) ** 2)
