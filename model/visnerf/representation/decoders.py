"""Encodings and the two small decoders (density, colour)."""

import math

import torch
from jaxtyping import Float
from torch import Tensor, nn

# Real spherical-harmonics constants, degrees 0..3 (as in Plenoxels / nerfstudio).
_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)


def sh_dim(degree: int) -> int:
    return (degree + 1) ** 2


def encode_sh(directions: Float[Tensor, "n 3"], degree: int) -> Float[Tensor, "n d"]:
    """Real spherical harmonics of unit directions, ``(degree + 1)^2`` values."""
    x, y, z = directions.unbind(-1)
    out = [torch.full_like(x, _C0)]
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [_C2[0] * xy, _C2[1] * yz, _C2[2] * (2 * zz - xx - yy), _C2[3] * xz, _C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            _C3[0] * y * (3 * xx - yy),
            _C3[1] * xy * z,
            _C3[2] * y * (4 * zz - xx - yy),
            _C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            _C3[4] * x * (4 * zz - xx - yy),
            _C3[5] * z * (xx - yy),
            _C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def positional_encoding_dim(n_freqs: int) -> int:
    return 3 + 6 * n_freqs


def encode_position(points: Float[Tensor, "n 3"], n_freqs: int) -> Float[Tensor, "n d"]:
    """``[x, sin(2^l pi x), cos(2^l pi x)]`` for l < n_freqs, coordinates in [-1, 1]."""
    feats = [points]
    for level in range(n_freqs):
        scaled = points * (math.pi * 2.0**level)
        feats += [torch.sin(scaled), torch.cos(scaled)]
    return torch.cat(feats, dim=-1)


def encode_position_into(points: Float[Tensor, "n 3"], n_freqs: int, out: Float[Tensor, "n d"]) -> None:
    """``encode_position`` written into ``out`` (any dtype) column block by column block, with
    no concatenation (inference)."""
    out[:, :3] = points
    for level in range(n_freqs):
        scaled = points * (math.pi * 2.0**level)
        out[:, 3 + 6 * level:6 + 6 * level] = torch.sin(scaled)
        out[:, 6 + 6 * level:9 + 6 * level] = torch.cos(scaled)


class Decoder(nn.Module):
    """One hidden layer MLP: ``in -> hidden -> out`` with ReLU.

    With ``bf16 = True`` the two matrix products run in bfloat16 (AMX / tensor cores) while the
    weights, the input and the returned output stay float32; everything downstream (softplus,
    transmittance, compositing) is float32.
    """

    def __init__(self, n_in: int, n_hidden: int, n_out: int) -> None:
        super().__init__()
        self.hidden = nn.Linear(n_in, n_hidden)
        self.out = nn.Linear(n_hidden, n_out)
        self.bf16 = False

    def forward(self, x: Float[Tensor, "n i"]) -> Float[Tensor, "n o"]:
        if self.bf16 and x.device.type in ("cpu", "cuda"):
            with torch.autocast(x.device.type, dtype=torch.bfloat16):
                return self.out(torch.relu(self.hidden(x))).float()
        return self.out(torch.relu(self.hidden(x)))
