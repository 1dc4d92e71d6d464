"""Encodings and the two small decoders (density, colour)."""

import functools
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


def padded_rows(m: int) -> int:
    """Rows a decoder pass of ``m`` samples is computed on: a multiple of 128 below 1024, of 1024
    above. oneDNN builds (JIT-compiles) a kernel for every new shape of a bf16 matrix product and
    caches it: with the sample count of every segment a new shape, that cost more than the
    arithmetic and its cache grew a server's memory without bound
    (docs/decisions.md#decoders.padded_rows). Rounded up, passes of up to 16384 samples use one of
    at most 24 shapes; the padding rows are zeros and their results are dropped."""
    step = 128 if m <= 1024 else 1024
    return max(step, -(-m // step) * step)


@functools.lru_cache(maxsize=8)
def _angle_map(n_freqs: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """(scales [3, 6L], phases [6L]): ``points @ scales + phases`` are the angles of every sine
    and cosine of ``encode_position`` in its column order (a cosine is the sine a quarter turn on)."""
    scales, phases = torch.zeros(3, 6 * n_freqs), torch.zeros(6 * n_freqs)
    for level in range(n_freqs):
        for axis in range(3):
            scales[axis, 6 * level + axis] = scales[axis, 6 * level + 3 + axis] = math.pi * 2.0**level
            phases[6 * level + 3 + axis] = 0.5 * math.pi
    return scales.to(device), phases.to(device)


def encode_position_into(points: Float[Tensor, "n 3"], n_freqs: int, out: Float[Tensor, "n d"]) -> None:
    """``encode_position`` written into ``out`` (any dtype), with one product for all angles and
    one sine (inference). The quarter-turn phase moves a cosine by at most one float32 rounding of
    its angle (angles below ``2^L pi``: 2e-7 for two levels; the tests bound it)."""
    out[:, :3] = points
    if n_freqs > 0:
        scales, phases = _angle_map(n_freqs, points.device)
        out[:, 3:] = torch.addmm(phases.to(points.dtype), points, scales.to(points.dtype)).sin_()


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
            n = x.shape[0]
            if x.device.type == "cpu":  # a few shapes for oneDNN's bf16 kernels (``padded_rows``)
                padded = x.new_empty((padded_rows(n), x.shape[1]), dtype=torch.bfloat16)
                padded[n:].zero_()
                padded[:n] = x  # cast once, into the padded rows (autocast would cast a padded copy)
                x = padded
            with torch.autocast(x.device.type, dtype=torch.bfloat16):
                return self.out(torch.relu(self.hidden(x)))[:n].float()
        return self.out(torch.relu(self.hidden(x)))
