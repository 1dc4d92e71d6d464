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
from jaxtyping import Float, Int
from torch import Tensor

from visnerf.representation.decoders import Decoder, encode_position_into, encode_sh, padded_rows
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


PLANE_U = tuple(a for (a, _), _ in MODES)
"""Grid axis along the width of each mode's plane: (0, 0, 1)."""
PLANE_V = tuple(b for (_, b), _ in MODES)
"""Grid axis along the height of each mode's plane: (1, 2, 2)."""
LINE_AXIS = tuple(c for _, c in MODES)
"""Grid axis of each mode's line: (2, 1, 0)."""


def _take(t: Tensor, index: Int[Tensor, " k"] | slice) -> Tensor:
    return t[index] if isinstance(index, slice) else t.index_select(0, index)


@dataclass(frozen=True)
class VMTaps:
    """Where a VM grid is read for ``m`` samples: for each of the three modes, the four plane rows
    and two line rows of its bilinear and linear interpolation, and their weights.

    The taps depend only on the grid's resolution, so the density and the appearance grid (same
    resolution) share them: colour reuses the taps its samples had for density.
    """

    plane_rows: Int[Tensor, "m 3 4"]
    plane_weights: Float[Tensor, "m 3 4"]
    line_rows: Int[Tensor, "m 3 2"]
    line_weights: Float[Tensor, "m 3 2"]

    def __len__(self) -> int:
        return self.plane_rows.shape[0]

    def select(self, index: Int[Tensor, " k"] | slice) -> "VMTaps":
        """Taps of samples ``index`` (a slice, or indices: ``index_select``, several times faster
        on the CPU than advanced indexing)."""
        return VMTaps(*(_take(t, index) for t in (self.plane_rows, self.plane_weights, self.line_rows, self.line_weights)))


@dataclass(frozen=True)
class TapLayout:
    """Where the taps of a grid of one resolution point into the stacked tables.

    Interpolation along an axis is the same in every mode that uses the axis (same node count),
    so the lower node and the fraction are computed once per axis. Everything after that is linear
    in them, or a product of two such things, and is written as small matrix products, which
    write contiguous rows (broadcasting over the trailing 3 x 4 taps was five times slower):

    - rows: ``lower @ row_matrix + row_offset`` (each plane row is ``offset + y0 * w + x0`` plus
      its corner's 0, 1, w or w + 1; each line row ``offset + z0`` plus 0 or 1);
    - weights: ``(1 - f, f)`` of each axis picked by 0/1 matrices (exact), the plane weight being
      the product of the picks of its two axes.
    """

    resolution: tuple[int, int, int]
    half_span: Float[Tensor, " 3"]
    """(n - 1) / 2 per axis: grid coordinate [-1, 1] to node position [0, n - 1]."""
    last_lower: Float[Tensor, " 3"]
    """n - 2 per axis: the highest lower node."""
    row_matrix: Float[Tensor, "3 18"]
    row_offset: Float[Tensor, " 18"]
    """Rows from the lower nodes: twelve plane taps (three modes of four corners), then six line
    taps (three modes of two nodes)."""
    weight_picks: Float[Tensor, "6 30"]
    """Pick from ``(1 - f, f)`` of the three axes: the weight along each plane tap's width axis
    (12), along its height axis (12), and each line tap's (6)."""

    @classmethod
    def of(cls, resolution: tuple[int, int, int], device: torch.device) -> "TapLayout":
        if min(resolution) < 2:
            raise ValueError(f"VM grid of resolution {resolution} has an axis with fewer than 2 nodes")
        plane_m, plane_o = torch.zeros(3, 12), torch.zeros(12)
        line_m, line_o = torch.zeros(3, 6), torch.zeros(6)
        pick_u, pick_v, pick_l = torch.zeros(6, 12), torch.zeros(6, 12), torch.zeros(6, 6)
        plane_start = line_start = 0
        # ``both`` holds (1 - f) of the three axes, then f of the three axes.
        for i, ((a, b), c) in enumerate(MODES):
            w, h, n = resolution[a], resolution[b], resolution[c]
            for k, (dx, dy) in enumerate(((0, 0), (1, 0), (0, 1), (1, 1))):
                col = 4 * i + k
                plane_m[a, col], plane_m[b, col] = 1.0, float(w)
                plane_o[col] = plane_start + dx + dy * w
                pick_u[a + 3 * dx, col] = 1.0
                pick_v[b + 3 * dy, col] = 1.0
            for k in (0, 1):
                col = 2 * i + k
                line_m[c, col] = 1.0
                line_o[col] = line_start + k
                pick_l[c + 3 * k, col] = 1.0
            plane_start += w * h
            line_start += n
        res = torch.tensor(resolution, dtype=torch.float32)
        return cls(
            resolution=resolution,
            half_span=(0.5 * (res - 1.0)).to(device),
            last_lower=(res - 2.0).to(device),
            row_matrix=torch.cat([plane_m, line_m], dim=1).to(device),
            row_offset=torch.cat([plane_o, line_o]).to(device),
            weight_picks=torch.cat([pick_u, pick_v, pick_l], dim=1).to(device),
        )

    def taps(self, coords: Float[Tensor, "m 3"], dtype: torch.dtype) -> VMTaps:
        """Taps of grid coordinates in [-1, 1] (outside reads the border); weights in ``dtype``.

        Row indices are exact in float32 below 2^24 rows."""
        m = coords.shape[0]
        pos = torch.addcmul(self.half_span, coords.clamp(-1.0, 1.0), self.half_span)  # [m, 3], in [0, n - 1]
        lower = torch.minimum(pos.floor(), self.last_lower)
        frac = pos - lower
        both = torch.cat([1.0 - frac, frac], dim=1)  # [m, 6]
        rows = torch.addmm(self.row_offset, lower, self.row_matrix)  # [m, 18]
        picks = both @ self.weight_picks  # [m, 30]
        plane_rows = rows[:, :12].to(torch.int32).contiguous().view(m, 3, 4)
        line_rows = rows[:, 12:].to(torch.int32).contiguous().view(m, 3, 2)
        plane_weights = torch.mul(picks[:, :12], picks[:, 12:24]).to(dtype).view(m, 3, 4)
        line_weights = picks[:, 24:].to(dtype).contiguous().view(m, 3, 2)
        return VMTaps(plane_rows, plane_weights, line_rows, line_weights)


@dataclass(frozen=True)
class ModeTables:
    """A VM grid's factors as two row tables for ``embedding_bag``: the three planes stacked
    (``[sum h * w, c]``, row ``offset + y * w + x``) and the three lines stacked (``[sum r, c]``).

    A lookup is then two fused weighted sums of rows for all three modes at once (four plane rows
    and two line rows per mode and sample), written row-major (``[m, 3, c]``), the layout the
    decoder's matrix product wants (``grid_sample`` writes channel-first, and the transpose cost
    as much as the lookup). Coordinates outside [-1, 1] read the border (inference only samples
    inside the box).
    """

    plane_table: Tensor
    line_table: Tensor
    layout: TapLayout
    n_components: int

    @classmethod
    def of(cls, grid: VMGrid, dtype: torch.dtype = torch.float32) -> "ModeTables":
        """Tables of ``grid`` in ``dtype``: in bfloat16 the lookups read half the bytes and their
        products are written in the decoders' compute type without a conversion."""
        layout = TapLayout.of(grid.resolution, grid.planes[0].device)
        planes = torch.cat([p.detach().permute(1, 2, 0).reshape(-1, p.shape[0]) for p in grid.planes])
        lines = torch.cat([li.detach().t() for li in grid.lines])
        return cls(planes.to(dtype).contiguous(), lines.to(dtype).contiguous(), layout, grid.n_components)

    def taps(self, coords: Float[Tensor, "m 3"]) -> VMTaps:
        return self.layout.taps(coords, self.plane_table.dtype)

    def features_into(self, taps: VMTaps, out: Float[Tensor, "m f"]) -> None:
        """Write ``VMGrid.sample`` at the taps' samples (plane times line per mode, modes
        concatenated) into ``out[:, :3c]``, in ``out``'s dtype (lookups in the tables' dtype)."""
        m, c = len(taps), self.n_components
        pf = F.embedding_bag(taps.plane_rows.view(-1, 4), self.plane_table,
                             per_sample_weights=taps.plane_weights.view(-1, 4), mode="sum")  # [3m, c]
        lf = F.embedding_bag(taps.line_rows.view(-1, 2), self.line_table,
                             per_sample_weights=taps.line_weights.view(-1, 2), mode="sum")  # [3m, c]
        torch.mul(pf.view(m, 3 * c), lf.view(m, 3 * c), out=out[:, : 3 * c])

    def features(self, coords: Float[Tensor, "m 3"], dtype: torch.dtype = torch.float32) -> Float[Tensor, "m f"]:
        out = torch.empty(coords.shape[0], 3 * self.n_components, dtype=dtype, device=coords.device)
        self.features_into(self.taps(coords), out)
        return out


@dataclass(frozen=True)
class SampleTaps:
    """Samples prepared for ``FrameField``: world points, grid coordinates and VM taps."""

    points: Float[Tensor, "m 3"]
    coords: Float[Tensor, "m 3"]
    taps: VMTaps

    def __len__(self) -> int:
        return self.points.shape[0]

    def select(self, index: Int[Tensor, " k"] | slice) -> "SampleTaps":
        return SampleTaps(_take(self.points, index), _take(self.coords, index), self.taps.select(index))


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
        if field.appearance_grid.resolution != field.density_grid.resolution:
            raise ValueError(f"density grid {field.density_grid.resolution} and appearance grid "
                             f"{field.appearance_grid.resolution} differ in resolution")
        dd, cd = field.density_decoder.out, field.color_decoder.out
        self._density_out = (dd.weight.detach().to(dtype), dd.bias.detach().to(dtype))
        self._color_out = (cd.weight.detach().to(dtype), cd.bias.detach().to(dtype))
        self._density_weight_t = torch.cat(  # [3c + e, h]: modes, then positional encoding
            [self.density_layer.spatial_weight_t, self.density_layer.rest_weight_t.to(dtype)], dim=0)
        self._density_bias = self.density_layer.bias.to(dtype)

    def lookup(self, points: Float[Tensor, "m 3"]) -> SampleTaps:
        """Grid coordinates and VM taps of ``points``, shared by density and colour."""
        coords = self.field.to_grid(points)
        return SampleTaps(points, coords, self.density_tables.taps(coords))

    def density(self, points: Float[Tensor, "m 3"]) -> Float[Tensor, " m"]:
        return self.density_at(self.lookup(points))

    def color(self, points: Float[Tensor, "m 3"], ray_terms: Float[Tensor, "m h"]) -> Float[Tensor, "m 3"]:
        """RGB at ``points``; ``ray_terms`` is ``direction_terms`` of each sample's ray."""
        return self.color_at(self.lookup(points).taps, ray_terms)

    def density_at(self, samples: SampleTaps) -> Float[Tensor, " m"]:
        out = torch.empty(len(samples), dtype=samples.points.dtype, device=samples.points.device)
        for start in range(0, len(samples), SUB_CHUNK):
            sl = slice(start, start + SUB_CHUNK)
            out[sl] = self._density(samples.coords[sl], samples.taps.select(sl))
        return out

    def _density(self, coords: Float[Tensor, "m 3"], taps: VMTaps) -> Float[Tensor, " m"]:
        cfg = self.field.cfg
        m = coords.shape[0]
        n_spatial = 3 * self.density_tables.n_components
        x = torch.empty(padded_rows(m), self._density_weight_t.shape[0], dtype=self.dtype, device=coords.device)
        x[m:].zero_()
        self.density_tables.features_into(taps, x[:m])
        encode_position_into(coords, cfg.pos_encoding_freqs, x[:m, n_spatial:])
        hidden = torch.addmm(self._density_bias, x, self._density_weight_t)  # [padded, h]
        raw = F.linear(hidden.relu_(), *self._density_out)[:m, 0].to(coords.dtype)
        return F.softplus(raw + cfg.density_shift)

    def direction_terms(self, directions: Float[Tensor, "a 3"]) -> Float[Tensor, "a h"]:
        """Per-ray part of the colour decoder's first layer (bias included), in the compute dtype."""
        sh = encode_sh(directions, self.field.cfg.sh_degree)
        return torch.addmm(self.color_layer.bias, sh, self.color_layer.rest_weight_t).to(self.dtype)

    def color_at(self, taps: VMTaps, ray_terms: Float[Tensor, "m h"]) -> Float[Tensor, "m 3"]:
        """RGB at samples with VM taps ``taps`` (``lookup(points).taps``); ``ray_terms`` is
        ``direction_terms`` of each sample's ray."""
        out = torch.empty(len(taps), 3, dtype=torch.float32, device=ray_terms.device)
        for start in range(0, len(taps), SUB_CHUNK):
            sl = slice(start, start + SUB_CHUNK)
            out[sl] = self._color(taps.select(sl), ray_terms[sl])
        return out

    def _color(self, taps: VMTaps, ray_terms: Float[Tensor, "m h"]) -> Float[Tensor, "m 3"]:
        m = len(taps)
        feats = torch.empty(padded_rows(m), 3 * self.appearance_tables.n_components, dtype=self.dtype,
                            device=ray_terms.device)
        feats[m:].zero_()
        self.appearance_tables.features_into(taps, feats[:m])  # [m, 3c]
        hidden = torch.mm(feats, self.color_layer.spatial_weight_t)  # [padded, h]
        hidden[:m] += ray_terms
        raw = F.linear(hidden.relu_(), *self._color_out)[:m]
        return torch.sigmoid(raw.float())
