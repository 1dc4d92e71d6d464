"""The field at one fixed parameter tuple, with the frame-constant work done once (inference).

Within a frame every sample shares the same parameter features ``q``. The field scales spatial
channel ``i`` by ``q[i % c]``, appends ``q`` and then applies the decoder's first linear layer, so
both steps fold into that layer: the spatial columns of its weight are scaled by ``q`` once and the
``q`` columns become part of the bias. The view direction's spherical harmonics depend only on
the ray: they are encoded once per ray and gathered per sample. What is left per sample is the VM
lookup and two matrix products, the first fused with its bias and ReLU (``linear_relu``); no
``[m, f]`` repeat or product with ``q``.

Two more things are done once per frame:

- the planes and lines are copied into row tables (``ModeTables``), so that a bilinear lookup is
  one fused weighted sum of rows (``embedding_bag``) whose output is already in the row-major
  layout the decoder's matrix product reads;
- with ``dtype=torch.bfloat16`` (where the device has bf16 matrix units, see
  ``runtime.bf16_native``) the folded weights and the row tables are cast once, and the lookups
  and matrix products run in bf16, as the decoders already do in training; coordinates,
  interpolation fractions, softplus, sigmoid and compositing stay float32: faster frames, the
  same 8-bit pixels (docs/decisions.md#frames.compiled_rows).

On the CPU the tables are not copied: one compiled pass per sample (``vm_kernel``) interpolates
the grid's own float32 tables and writes the decoder's input row (features, and the positional
encoding for density), rounded once to the compute dtype; ``ModeTables`` and ``TapLayout`` serve
every other device. There too, in bfloat16, each decoder's output layer sums the activations in
float32 and is written in float32 (``output_kernel``): oneDNN's product rounds its output to
bfloat16. bench/results/render_speed.md measures the whole renderer against the
exhaustive float32 one.

With float32 the result equals ``VisNerfField.density`` / ``color`` up to float rounding; with
bfloat16 it differs by the rounding of the products (both tested).
"""

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from jaxtyping import Float, Int
from torch import Tensor

from visnerf.representation import output_kernel, vm_kernel
from visnerf.representation.decoders import Decoder, encode_position_into, encode_sh, padded_rows
from visnerf.representation.field import (
    N_PROBES,
    VisNerfField,
    facing_cosines,
    level_cosines,
    probe_points,
)
from visnerf.representation.linear_relu import linear_relu
from visnerf.representation.vm import VMGrid
from visnerf.representation.vm_taps import TapLayout, VMTaps, lookup_modes, take_rows
from visnerf.runtime import batch_factor

SUB_CHUNK = 16384
"""Samples decoded per pass on the CPU: the hidden activations of one pass stay in the core's cache
(``runtime.batch_factor`` times more on a GPU)."""



@dataclass(frozen=True)
class FoldedLayer:
    """First decoder layer with the parameter features folded in, as ``linear_relu`` takes it."""

    weight: Float[Tensor, "h i"]
    """Columns of the three VM modes, scaled by the parameter features, then those of the trailing
    encoding (positional or spherical harmonics); compute dtype."""
    bias: Float[Tensor, " h"]
    """Layer bias plus the product of the ``q`` columns with ``q`` (summed in float32); compute dtype."""


def fold_first_layer(decoder: Decoder, q: Float[Tensor, " c"], n_components: int, dtype: torch.dtype) -> FoldedLayer:
    """Fold parameter features ``q`` into ``decoder.hidden``.

    The layer's input is ``[spatial * q_rep, q, rest]`` with ``spatial`` the three VM modes of
    ``n_components`` channels each, concatenated; the folded layer's input is ``[spatial, rest]``.
    """
    w, b = decoder.hidden.weight.detach(), decoder.hidden.bias.detach()  # [h, n_in], [h]
    c = q.shape[0]
    n_spatial = 3 * n_components
    scaled = w[:, :n_spatial] * q.repeat(n_spatial // c)[None]  # [h, f]
    return FoldedLayer(
        weight=torch.cat([scaled, w[:, n_spatial + c:]], dim=1).to(dtype).contiguous(),
        bias=(b + w[:, n_spatial:n_spatial + c] @ q).to(dtype),
    )


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
        planes, lines = (t.detach().to(dtype).contiguous() for t in grid.row_tables())
        return cls(planes, lines, grid.tap_layout(), grid.n_components)

    def taps(self, coords: Float[Tensor, "m 3"]) -> VMTaps:
        return self.layout.taps(coords, self.plane_table.dtype)

    def features_into(self, taps: VMTaps, out: Float[Tensor, "m f"]) -> None:
        """Write ``VMGrid.sample`` at the taps' samples (plane times line per mode, modes
        concatenated) into ``out[:, :3c]``, in ``out``'s dtype (lookups in the tables' dtype)."""
        m, c = len(taps), self.n_components
        pf, lf = lookup_modes(taps, self.plane_table, self.line_table)  # [3m, c] each
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
    taps: VMTaps | None
    """None where the compiled pass (``vm_kernel``) reads the grids: it interpolates from ``coords``."""

    def __len__(self) -> int:
        return self.points.shape[0]

    def select(self, index: Int[Tensor, " k"] | slice) -> "SampleTaps":
        taps = None if self.taps is None else self.taps.select(index)
        return SampleTaps(take_rows(self.points, index), take_rows(self.coords, index), taps)


class FrameField:
    """Density and colour of ``field`` at parameter features (q_density, q_appearance), no grad.

    ``dtype`` is the compute type of the decoders' matrix products (float32 or bfloat16). On the
    CPU the decoders' input rows are written by one compiled pass per sample (``vm_kernel``) and a
    bfloat16 output layer by another (``output_kernel``); ``compiled=False`` takes the torch
    operations every device has.
    """

    def __init__(
        self,
        field: VisNerfField,
        q_density: Float[Tensor, "1 d"],
        q_appearance: Float[Tensor, "1 c"],
        dtype: torch.dtype = torch.float32,
        compiled: bool = True,
    ) -> None:
        self.field = field
        self.dtype = dtype
        self.sub_chunk = SUB_CHUNK * batch_factor(q_density.device)
        """Samples decoded per pass."""
        cfg = field.cfg
        q_factors, level = field.split_density_features(q_density)
        self.density_layer = fold_first_layer(field.density_decoder, q_factors[0], cfg.n_density_components, dtype)
        # a level axis's level is constant within the frame: it joins the shift before the softplus,
        # and its sharpness scales the decoder's output layer
        sharpness = 1.0 if field.levels is None else float(field.levels.sharpness().detach())
        self._density_shift = cfg.density_shift - (0.0 if level is None else sharpness * float(level[0].detach()))
        self.color_layer = fold_first_layer(field.color_decoder, q_appearance[0], cfg.n_appearance_components, dtype)
        self.compiled = compiled and vm_kernel.available(q_density.device)
        """Whether the compiled pass fills the decoders' input rows (else ``ModeTables``)."""
        self.density_tables = self.appearance_tables = None
        self.density_kernel = self.appearance_kernel = None
        if self.compiled:
            self.density_kernel = vm_kernel.KernelTables.of(*field.density_grid.row_tables(),
                                                            field.density_grid.resolution)
            self.appearance_kernel = vm_kernel.KernelTables.of(*field.appearance_grid.row_tables(),
                                                               field.appearance_grid.resolution)
        else:
            self.density_tables = ModeTables.of(field.density_grid, dtype)
            self.appearance_tables = ModeTables.of(field.appearance_grid, dtype)
        if field.appearance_grid.resolution != field.density_grid.resolution:
            raise ValueError(f"density grid {field.density_grid.resolution} and appearance grid "
                             f"{field.appearance_grid.resolution} differ in resolution")
        self._facing: Tensor | None = None
        if field.facing is not None:  # the facing map reads the modulated features: fold q in too
            c = q_appearance.shape[1]
            n_spatial = 3 * cfg.n_appearance_components
            scaled = field.facing.weight.detach() * q_appearance[0].repeat(n_spatial // c)[None]  # [3m, f]
            self._facing = scaled.to(dtype).contiguous()
        dd, cd = field.density_decoder.out, field.color_decoder.out
        self._density_out = ((dd.weight.detach() * sharpness).to(dtype), (dd.bias.detach() * sharpness).to(dtype))
        self._color_out = (cd.weight.detach().to(dtype), cd.bias.detach().to(dtype))
        self._density_out_f32 = self._color_out_f32 = None
        """The output layers in float32 on bfloat16 activations (``output_kernel``): the compiled path."""
        if dtype == torch.bfloat16 and self.compiled and output_kernel.available(q_density.device):
            self._density_out_f32 = output_kernel.OutputLayer(dd.weight.detach() * sharpness,
                                                              dd.bias.detach() * sharpness)
            self._color_out_f32 = output_kernel.OutputLayer(cd.weight, cd.bias)
        self._level_step = None if field.levels is None else cfg.level_normal_step * field.voxel_size()
        # [3], world units to grid coordinates (``to_grid``)
        self._grid_scale = 2.0 / field.grid_extent(field.aabb.dtype)
        self._grid_offset = -field.aabb[0] * self._grid_scale - 1.0  # [3]
        self._with_directions = self._facing is not None or self._level_step is not None

    def lookup(self, points: Float[Tensor, "m 3"]) -> SampleTaps:
        """Grid coordinates and VM taps of ``points``, shared by density and colour."""
        # ``VisNerfField.to_grid`` as one fused multiply-add (four operations and the box's
        # extent every call before); the coordinates differ by float rounding
        coords = torch.addcmul(self._grid_offset.to(points.dtype), points, self._grid_scale.to(points.dtype))
        if self.density_tables is None:
            return SampleTaps(points, coords, None)
        return SampleTaps(points, coords, self.density_tables.taps(coords))

    def density(self, points: Float[Tensor, "m 3"]) -> Float[Tensor, " m"]:
        return self.density_at(self.lookup(points))

    def color(self, points: Float[Tensor, "m 3"], ray_terms: Float[Tensor, "m e"]) -> Float[Tensor, "m 3"]:
        """RGB at ``points``; ``ray_terms`` is ``direction_terms`` of each sample's ray."""
        return self.color_at(self.lookup(points), ray_terms)

    def density_at(self, samples: SampleTaps) -> Float[Tensor, " m"]:
        out = torch.empty(len(samples), dtype=samples.points.dtype, device=samples.points.device)
        return self._by_pass(samples, self._density, out)

    def _by_pass(self, samples: SampleTaps, decode: Callable[[Tensor, VMTaps | None], Tensor],
                 out: Float[Tensor, " m"]) -> Float[Tensor, " m"]:
        """``out`` filled with ``decode(coords, taps)`` of ``samples``, ``sub_chunk`` samples a pass."""
        for start in range(0, len(samples), self.sub_chunk):
            sl = slice(start, start + self.sub_chunk)
            out[sl] = decode(samples.coords[sl], samples.select(sl).taps)
        return out

    def _appearance_rows(self, samples: SampleTaps, out: Tensor) -> None:
        """The appearance features of ``samples`` written into ``out[:, :3c]`` (compiled pass or tables)."""
        if self.appearance_kernel is not None:
            self.appearance_kernel.write_rows(samples.coords, out)
        else:
            assert self.appearance_tables is not None and samples.taps is not None
            self.appearance_tables.features_into(samples.taps, out)

    def _density(self, coords: Float[Tensor, "m 3"], taps: VMTaps | None) -> Float[Tensor, " m"]:
        return F.softplus(self._raw_density(coords, taps) + self._density_shift) * self.field.cfg.density_scale

    def _raw_density(self, coords: Float[Tensor, "m 3"], taps: VMTaps | None) -> Float[Tensor, " m"]:
        """The density decoder's output (a level axis's ``g`` times its sharpness), float32."""
        cfg = self.field.cfg
        m = coords.shape[0]
        x = torch.empty(padded_rows(m), self.density_layer.weight.shape[1], dtype=self.dtype, device=coords.device)
        x[m:].zero_()
        if self.density_kernel is not None:
            self.density_kernel.write_rows(coords, x[:m], cfg.pos_encoding_freqs)
        else:
            assert self.density_tables is not None and taps is not None
            self.density_tables.features_into(taps, x[:m])
            encode_position_into(coords, cfg.pos_encoding_freqs, x[:m, 3 * self.density_tables.n_components:])
        hidden = linear_relu(x, self.density_layer.weight, self.density_layer.bias)  # [padded, h]
        if self._density_out_f32 is not None:
            return self._density_out_f32(hidden[:m])[:, 0]
        return F.linear(hidden, *self._density_out)[:m, 0].to(coords.dtype)

    def direction_terms(self, directions: Float[Tensor, "a 3"]) -> Float[Tensor, "a e"]:
        """The view direction's spherical harmonics per ray, in the compute dtype: encoded once
        per ray, gathered per sample into the colour decoder's input (``e`` = 16 columns at
        degree 3; gathering the per-ray product with the first layer instead moved 128 columns
        per sample and cost more than the product it saved)."""
        sh = encode_sh(directions, self.field.cfg.sh_degree)
        if not self._with_directions:
            return sh.to(self.dtype)
        # the direction itself follows for the facing cosines, kept in float32 so that it adds no
        # rounding of its own (a cosine to the 40th moves by 8 % of its height per bf16 rounding of
        # the cosine); the learnt vectors come from the features in the compute dtype, as every
        # decoder input does
        return torch.cat([sh, directions.float()], dim=-1)

    def color_at(self, samples: SampleTaps, ray_terms: Float[Tensor, "m e"]) -> Float[Tensor, "m 3"]:
        """RGB at ``samples`` (``lookup(points)``); ``ray_terms`` is ``direction_terms`` of each
        sample's ray."""
        out = torch.empty(len(samples), 3, dtype=torch.float32, device=ray_terms.device)
        for start in range(0, len(samples), self.sub_chunk):
            sl = slice(start, start + self.sub_chunk)
            out[sl] = self._color(samples.select(sl), ray_terms[sl])
        return out

    def _level_cosines(self, points: Float[Tensor, "m 3"], directions: Float[Tensor, "m 3"]) -> Float[Tensor, "m p"]:
        """``level_cosines`` of the level field at ``points``, as ``VisNerfField.level_normal_cosines``."""
        return level_cosines(self.level_probes(points), directions, self.field.cfg.level_cosine_powers)

    def level_probes(self, points: Float[Tensor, "m 3"]) -> Float[Tensor, "m 4"]:
        """The level field (times its sharpness) at the ``TETRAHEDRON`` probes of each point, the
        input of ``level_cosines``; a field without a level axis has none (ValueError)."""
        if self._level_step is None:
            raise ValueError("the field has no level axis: its colour reads no normal")
        probes = self.lookup(probe_points(points, self._level_step))  # N_PROBES rows a point
        raw = torch.empty(len(probes), dtype=points.dtype, device=points.device)
        return self._by_pass(probes, self._raw_density, raw).view(-1, N_PROBES)

    @property
    def level_step(self) -> float | None:
        """World distance of the normal's probes from a point; None without a level axis."""
        return self._level_step

    @property
    def density_activation(self) -> tuple[float, float]:
        """(shift, scale): the density is ``softplus(raw_density + shift) * scale``."""
        return self._density_shift, self.field.cfg.density_scale

    def raw_density(self, points: Float[Tensor, "m 3"]) -> Float[Tensor, " m"]:
        """The density before its activation (``density_activation``): a level axis's sharpened
        ``g``, float32."""
        samples = self.lookup(points)
        out = torch.empty(len(samples), dtype=torch.float32, device=points.device)
        return self._by_pass(samples, self._raw_density, out)

    def view_logits(self, points: Float[Tensor, "m 3"], directions: Float[Tensor, "m v 3"],
                    probes: Float[Tensor, "m 4"] | None = None) -> Float[Tensor, "m v 3"]:
        """The colour decoder's output before its sigmoid at each point seen along each of its
        ``v`` unit directions: the appearance features, the learnt vectors and the level field's
        normal are looked up once a point, the first layer's spatial part is applied once a
        point. ``probes``: ``level_probes(points)`` where the caller has them. Equals ``color``
        through a logit (float rounding; tested)."""
        m, v = directions.shape[:2]
        samples = self.lookup(points)
        n_spatial = 3 * self.field.cfg.n_appearance_components
        feats = torch.empty(m, n_spatial, dtype=self.dtype, device=points.device)
        self._appearance_rows(samples, feats)
        weight, bias = self.color_layer.weight, self.color_layer.bias  # [h, i], [h]
        base = F.linear(feats, weight[:, :n_spatial], bias).float()  # [m, h]
        flat_dirs = directions.reshape(m * v, 3).float()
        parts = [encode_sh(flat_dirs, self.field.cfg.sh_degree)]
        if self._facing is not None:
            vectors = F.linear(feats, self._facing).float()  # [m, 3f]
            parts.append(facing_cosines(vectors.repeat_interleave(v, dim=0), flat_dirs))
        if self._level_step is not None:
            probes = self.level_probes(points) if probes is None else probes
            parts.append(level_cosines(probes.repeat_interleave(v, dim=0), flat_dirs,
                                       self.field.cfg.level_cosine_powers))
        rest = torch.cat(parts, dim=1).to(self.dtype)  # [m v, r]
        hidden = F.linear(rest, weight[:, n_spatial:]).float().view(m, v, -1) + base[:, None, :]
        out_w, out_b = self._color_out
        return F.linear(torch.relu(hidden), out_w.float(), out_b.float())  # [m, v, 3]

    def _color(self, samples: SampleTaps, ray_terms: Float[Tensor, "m e"]) -> Float[Tensor, "m 3"]:
        m = len(samples)
        n_spatial = 3 * self.field.cfg.n_appearance_components
        x = torch.empty(padded_rows(m), self.color_layer.weight.shape[1], dtype=self.dtype, device=ray_terms.device)
        x[m:].zero_()
        self._appearance_rows(samples, x[:m])  # [m, 3c]
        if not self._with_directions:
            x[:m, n_spatial:] = ray_terms
        else:
            n_sh = ray_terms.shape[1] - 3
            directions = ray_terms[:, n_sh:]
            x[:m, n_spatial:n_spatial + n_sh] = ray_terms[:, :n_sh]
            column = n_spatial + n_sh
            if self._facing is not None:
                # on the padded rows, as the decoder's products: a bf16 product of every new row count
                # is a new oneDNN kernel, cached, and that cache grew a server frame after frame
                vectors = F.linear(x[:, :n_spatial], self._facing)[:m]  # [m, 3v]
                cosines = facing_cosines(vectors, directions)
                x[:m, column:column + cosines.shape[1]] = cosines.to(self.dtype)
                column += cosines.shape[1]
            if self._level_step is not None:
                level = self._level_cosines(samples.points, directions)  # [m, 1 + powers]
                x[:m, column:column + level.shape[1]] = level.to(self.dtype)
        hidden = linear_relu(x, self.color_layer.weight, self.color_layer.bias)  # [padded, h]
        if self._color_out_f32 is not None:
            return torch.sigmoid(self._color_out_f32(hidden[:m]))
        raw = F.linear(hidden, *self._color_out)[:m]
        return torch.sigmoid(raw.float())
