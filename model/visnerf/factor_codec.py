"""Row-wise int8 codes of the VM planes, for checkpoints (``FieldConfig.factor_storage="int8"``).

A plane ``[c, h, w]`` is stored as int8 codes of the same shape and one float32 scale per row of
``w`` values, ``[c, h, 1]``: ``x ~ code * scale`` with ``scale = max |x| / 127`` over the row, so
each value is off by at most half a step (``scale / 2``) and an all-zero row is exact. A row
holds one component along one axis of a plane, so one bright filament sets the step of its own row
only, not of the whole plane. The scales add ``4 / w`` bytes per value (under 2 % at w = 240).
"""

import torch
from jaxtyping import Float, Int8
from torch import Tensor

CODE_MAX = 127
"""Largest code magnitude: symmetric codes -127..127 (-128 is never written)."""

ROW_SCALE_SUFFIX = ".row_scale"
"""Name of a coded plane's scales in a checkpoint: the plane's own name plus this suffix."""


def encode_rows(values: Float[Tensor, "*b w"]) -> tuple[Int8[Tensor, "*b w"], Float[Tensor, "*b 1"]]:
    """Symmetric int8 codes along the last axis and their float32 scales (0 for a row of zeros).

    Raises ``ValueError`` for non-finite values: a code cannot hold them."""
    values = values.detach().to(torch.float32)
    if not bool(torch.isfinite(values).all()):
        raise ValueError("cannot code non-finite values as int8")
    scale = values.abs().amax(dim=-1, keepdim=True) / CODE_MAX  # [*b, 1]
    safe = torch.where(scale > 0, scale, torch.ones_like(scale))
    codes = torch.round(values / safe).clamp_(-CODE_MAX, CODE_MAX).to(torch.int8)
    return codes, scale


def decode_rows(codes: Int8[Tensor, "*b w"], scale: Float[Tensor, "*b 1"]) -> Float[Tensor, "*b w"]:
    """float32 values of int8 codes: ``code * scale``."""
    return codes.to(torch.float32) * scale.to(torch.float32)
