"""The field at one fixed parameter tuple, with the frame-constant work done once (inference).

Within a frame every sample shares the same parameter features ``q``. The field scales spatial
channel ``i`` by ``q[i % c]``, appends ``q`` and then applies the decoder's first linear layer, so
both steps fold into that layer: the spatial columns of its weight are scaled by ``q`` once and the
``q`` columns become part of the bias. The colour decoder's view-direction columns depend only on
the ray, so their product is taken once per ray instead of once per sample. What is left per
sample is the VM lookup and two matrix products; no ``[m, f]`` repeat or product with ``q``.

Two more things are done once per frame:

- the planes and lines are copied into row tables (``ModeTables``), so that a bilinear lookup is
  one fused weighted sum of rows (``embedding_bag``) whose output is already in the row-major
  layout the decoder's matrix product reads;
- with ``dtype=torch.bfloat16`` (where the device has bf16 matrix units, see
  ``runtime.bf16_native``) the folded weights and the row tables are cast once, and the lookups
  and matrix products run in bf16, as the decoders already do in training; coordinates,
  interpolation fractions, softplus, sigmoid and compositing stay float32. bf16 tables made full
  frames of the bundled checkpoints 12 to 15 % faster than float32 tables, 64 dB apart (8-bit
  frames, measured side by side).

bench/results/render_speed.md measures the whole renderer against the exhaustive float32 one.

With float32 the result equals ``VisNerfField.density`` / ``color`` up to float rounding; with
bfloat16 it differs by the rounding of the products (both tested).
"""

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor

from visnerf.representation.decoders import Decoder, encode_position, encode_sh
from visnerf.representation.field import VisNerfField
from visnerf.representation.vm import MODES, VMGrid

SUB_CHUNK = 16384
"""Samples decoded per pass: the hidden activations of one pass stay in the core's cache."""


@dataclass(frozen=True)
class FoldedLayer:
    """First decoder layer with the parameter features folded in, transposed for ``x @ w``."""

    spatial_weight_t: Float[Tensor, "f h"]
    """Columns of the three VM modes, scaled by the parameter features (compute dtype)."""
    rest_weight_t: Float[Tensor, "e h"]
    """Columns of the trailing encoding (positional or spherical harmonics), float32."""
    bias: Float[Tensor, " h"]
    """Layer bias plus the product of the ``q`` columns with ``q``, float32."""


def fold_first_layer(decoder: Decoder, q: Float[Tensor, " c"], n_components: int, dtype: torch.dtype) -> FoldedLayer:
    """Fold parameter features ``q`` into ``decoder.hidden``.

    The layer's input is ``[spatial * q_rep, q, rest]`` with ``spatial`` the three VM modes of
    ``n_components`` channels each, concatenated.
    """
    w, b = decoder.hidden.weight.detach(), decoder.hidden.bias.detach()  # [h, n_in], [h]
    c = q.shape[0]
    n_spatial = 3 * n_components
    scaled = w[:, :n_spatial] * q.repeat(n_spatial // c)[None]  # [h, f]
    return FoldedLayer(
        spatial_weight_t=scaled.t().contiguous().to(dtype),
        rest_weight_t=w[:, n_spatial + c:].t().contiguous(),
        bias=b + w[:, n_spatial:n_spatial + c] @ q,
    )


def linear_taps(u: Float[Tensor, " m"], n: int) -> tuple[Float[Tensor, " m"], Float[Tensor, " m"]]:
    """Lower node and fraction of linear interpolation on ``n`` nodes spanning [-1, 1]
    (``align_corners=True``); coordinates outside are clamped to the border. Returns float nodes."""
    pos = (u.clamp(-1.0, 1.0) + 1.0) * (0.5 * (n - 1))
    lo = pos.floor().clamp_(0, n - 2)
    return lo, pos - lo


@dataclass(frozen=True)
class ModeTables:
    """A VM grid's factors as row tables for ``embedding_bag``: each plane ``[h * w, c]`` (row
    ``y * w + x``), each line ``[r, c]``.

    A bilinear lookup is then one fused weighted sum of four rows per sample, written row-major
    (``[m, c]``), which is the layout the decoder's matrix product wants (``grid_sample`` writes
    channel-first, and the transpose cost as much as the lookup). Coordinates outside [-1, 1] read
    the border (inference only samples inside the box).
    """

    planes: tuple[Tensor, ...]
    plane_sizes: tuple[tuple[int, int], ...]
    """(h, w) of each plane."""
    lines: tuple[Tensor, ...]
    n_components: int

    @classmethod
    def of(cls, grid: VMGrid, dtype: torch.dtype = torch.float32) -> "ModeTables":
        """Tables of ``grid`` in ``dtype``: in bfloat16 the lookups read half the bytes and their
        products are written in the decoders' compute type without a conversion."""
        planes = tuple(p.detach().permute(1, 2, 0).reshape(-1, p.shape[0]).to(dtype).contiguous() for p in grid.planes)
        sizes = tuple((int(p.shape[1]), int(p.shape[2])) for p in grid.planes)
        lines = tuple(li.detach().t().to(dtype).contiguous() for li in grid.lines)
        if min(min(hw) for hw in sizes) < 2 or min(li.shape[0] for li in lines) < 2:
            raise ValueError(f"VM grid of resolution {grid.resolution} has an axis with fewer than 2 nodes")
        return cls(planes=planes, plane_sizes=sizes, lines=lines, n_components=grid.n_components)

    def features_into(self, coords: Float[Tensor, "m 3"], out: Float[Tensor, "m f"]) -> None:
        """Write ``VMGrid.sample(coords)`` (plane times line per mode, modes concatenated) into
        ``out[:, :3c]``, in ``out``'s dtype (the lookups run in the tables' dtype)."""
        c = self.n_components
        for i, (((a, b), axis), plane, (h, w), line) in enumerate(
            zip(MODES, self.planes, self.plane_sizes, self.lines, strict=True)
        ):
            x0, fx = linear_taps(coords[:, a], w)
            y0, fy = linear_taps(coords[:, b], h)
            row = (y0 * w + x0).long()
            idx = row[:, None] + torch.tensor([0, 1, w, w + 1], device=row.device)  # [m, 4]
            gx, gy = 1.0 - fx, 1.0 - fy
            weights = torch.stack([gx * gy, fx * gy, gx * fy, fx * fy], dim=1).to(plane.dtype)
            pf = F.embedding_bag(idx, plane, per_sample_weights=weights, mode="sum")  # [m, c]
            l0, fl = linear_taps(coords[:, axis], line.shape[0])
            l0 = l0.long()
            lf = F.embedding_bag(l0[:, None] + torch.tensor([0, 1], device=l0.device), line,
                                 per_sample_weights=torch.stack([1.0 - fl, fl], dim=1).to(line.dtype), mode="sum")
            torch.mul(pf, lf, out=out[:, i * c:(i + 1) * c])

    def features(self, coords: Float[Tensor, "m 3"], dtype: torch.dtype = torch.float32) -> Float[Tensor, "m f"]:
        out = torch.empty(coords.shape[0], 3 * self.n_components, dtype=dtype, device=coords.device)
        self.features_into(coords, out)
        return out


class FrameField:
    """Density and colour of ``field`` at parameter features (q_density, q_appearance), no grad.

    ``dtype`` is the compute type of the decoders' matrix products (float32 or bfloat16).
    """

    def __init__(
        self,
        field: VisNerfField,
        q_density: Float[Tensor, "1 c"],
        q_appearance: Float[Tensor, "1 c"],
        dtype: torch.dtype = torch.float32,
    ) -> None:
        self.field = field
        self.dtype = dtype
        cfg = field.cfg
        self.density_layer = fold_first_layer(field.density_decoder, q_density[0], cfg.n_density_components, dtype)
        self.color_layer = fold_first_layer(field.color_decoder, q_appearance[0], cfg.n_appearance_components, dtype)
        self.density_tables = ModeTables.of(field.density_grid, dtype)
        self.appearance_tables = ModeTables.of(field.appearance_grid, dtype)
        dd, cd = field.density_decoder.out, field.color_decoder.out
        self._density_out = (dd.weight.detach().to(dtype), dd.bias.detach().to(dtype))
        self._color_out = (cd.weight.detach().to(dtype), cd.bias.detach().to(dtype))
        self._density_weight_t = torch.cat(  # [3c + e, h]: modes, then positional encoding
            [self.density_layer.spatial_weight_t, self.density_layer.rest_weight_t.to(dtype)], dim=0)
        self._density_bias = self.density_layer.bias.to(dtype)

    def density(self, points: Float[Tensor, "m 3"]) -> Float[Tensor, " m"]:
        out = torch.empty(points.shape[0], dtype=points.dtype, device=points.device)
        for start in range(0, points.shape[0], SUB_CHUNK):
            out[start:start + SUB_CHUNK] = self._density(points[start:start + SUB_CHUNK])
        return out

    def _density(self, points: Float[Tensor, "m 3"]) -> Float[Tensor, " m"]:
        f = self.field
        coords = f.to_grid(points)
        n_spatial = 3 * self.density_tables.n_components
        x = torch.empty(points.shape[0], self._density_weight_t.shape[0], dtype=self.dtype, device=points.device)
        self.density_tables.features_into(coords, x)
        x[:, n_spatial:] = encode_position(coords, f.cfg.pos_encoding_freqs)
        hidden = torch.addmm(self._density_bias, x, self._density_weight_t)  # [m, h]
        raw = F.linear(hidden.relu_(), *self._density_out)[:, 0].to(points.dtype)
        return F.softplus(raw + f.cfg.density_shift)

    def direction_terms(self, directions: Float[Tensor, "a 3"]) -> Float[Tensor, "a h"]:
        """Per-ray part of the colour decoder's first layer (bias included), in the compute dtype."""
        sh = encode_sh(directions, self.field.cfg.sh_degree)
        return torch.addmm(self.color_layer.bias, sh, self.color_layer.rest_weight_t).to(self.dtype)

    def color(self, points: Float[Tensor, "m 3"], ray_terms: Float[Tensor, "m h"]) -> Float[Tensor, "m 3"]:
        """RGB at ``points``; ``ray_terms`` is ``direction_terms`` of each sample's ray."""
        out = torch.empty(points.shape[0], 3, dtype=points.dtype, device=points.device)
        for start in range(0, points.shape[0], SUB_CHUNK):
            sl = slice(start, start + SUB_CHUNK)
            out[sl] = self._color(points[sl], ray_terms[sl])
        return out

    def _color(self, points: Float[Tensor, "m 3"], ray_terms: Float[Tensor, "m h"]) -> Float[Tensor, "m 3"]:
        coords = self.field.to_grid(points)
        feats = self.appearance_tables.features(coords, self.dtype)  # [m, 3c]
        hidden = torch.addmm(ray_terms, feats, self.color_layer.spatial_weight_t)  # [m, h]
        raw = F.linear(hidden.relu_(), *self._color_out)
        return torch.sigmoid(raw.to(points.dtype))
