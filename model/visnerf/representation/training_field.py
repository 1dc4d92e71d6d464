"""The field as the fused training step evaluates it (CPU): compiled lookups, row-sparse gradients.

``TrainingField`` computes what ``VisNerfField.density`` and ``color`` compute, at compact samples
whose parameter features are their rays' (``q[ray]``): each grid's decoder rows come from one
compiled loop (``vm_rows.GridRows``), the decoders, the level and the facing cosines are the
field's own modules. Differentiable in the decoders and parameter tables (autograd) and in the VM
tables, whose gradients are left as pending taps in ``RowGradients`` (``table_gradients``).
"""

import torch
import torch.nn.functional as F
from jaxtyping import Float, Int
from torch import Tensor

from visnerf.representation.decoders import encode_sh
from visnerf.representation.field import N_PROBES, VisNerfField, facing_cosines, level_cosines, probe_points
from visnerf.representation.param_axes import distinct_rows
from visnerf.representation.table_gradients import RowGradients
from visnerf.representation.vm_rows import GridRows, TakenRows


class TrainingField:
    """``field`` read through the compiled lookups, its VM gradients kept in ``density_grads`` and
    ``appearance_grads`` (``RowGradients``, made here: ``follows`` says when the grids' tables
    have been replaced and a new one is needed)."""

    def __init__(self, field: VisNerfField) -> None:
        self.field = field
        self.density_grads = RowGradients.of(field.density_grid)
        self.appearance_grads = RowGradients.of(field.appearance_grid)
        self.density_rows = GridRows(field.density_grid, self.density_grads)
        self.appearance_rows = GridRows(field.appearance_grid, self.appearance_grads)

    def follows(self, field: VisNerfField) -> bool:
        """Whether this still reads ``field``'s current tables (resampling replaces them)."""
        return (field is self.field and self.density_grads.follows(field.density_grid)
                and self.appearance_grads.follows(field.appearance_grid))

    def row_gradients(self) -> tuple[RowGradients, RowGradients]:
        return self.density_grads, self.appearance_grads

    def param_features(self, params: Float[Tensor, "n k"]) -> tuple[Float[Tensor, "n d"], Float[Tensor, "n c"]]:
        """``VisNerfField.param_features``, computed once per distinct parameter row (a batch's
        rays hold a few dozen training settings) and gathered per ray: the same values, a few
        thousand times less arithmetic, and its backward a sum per setting."""
        if params.shape[1] == 0:
            return self.field.param_features(params)
        settings, which = distinct_rows(params)
        q_d, q_a = self.field.param_features(settings)
        return q_d.index_select(0, which), q_a.index_select(0, which)

    def raw_density(
        self, coords: Float[Tensor, "m 3"], ray: Int[Tensor, " m"], q_factors: Float[Tensor, "n c"]
    ) -> Float[Tensor, " m"]:
        """``VisNerfField.raw_density`` at grid coordinates, ``q_factors[ray]`` per sample."""
        rows = self.density_rows.rows(coords, ray, q_factors, self.field.cfg.pos_encoding_freqs)
        return self.field.density_decoder(rows)[:, 0]

    def _density_of_raw(self, raw: Float[Tensor, " m"], ray: Int[Tensor, " m"], level: Tensor | None) -> Tensor:
        field = self.field
        if level is not None and field.levels is not None:
            raw = (raw - level.index_select(0, ray)) * field.levels.sharpness()
        return F.softplus(raw + field.cfg.density_shift) * field.cfg.density_scale

    def density(
        self, points: Float[Tensor, "m 3"], ray: Int[Tensor, " m"], q_density: Float[Tensor, "n d"]
    ) -> Float[Tensor, " m"]:
        """``VisNerfField.density`` at world points with ``q_density[ray]`` per sample."""
        field = self.field
        q, level = field.split_density_features(q_density)
        return self._density_of_raw(self.raw_density(field.to_grid(points), ray, q), ray, level)

    @torch.no_grad()
    def density_taken(
        self, points: Float[Tensor, "m 3"], ray: Int[Tensor, " m"], q_density: Float[Tensor, "n d"]
    ) -> tuple[Float[Tensor, " m"], TakenRows]:
        """``density`` without a graph, and the decoder rows it read, from which
        ``density_of_taken`` makes any subset differentiable without reading the grid again."""
        field = self.field
        q, level = field.split_density_features(q_density)
        taken = self.density_rows.take(field.to_grid(points), ray, q, field.cfg.pos_encoding_freqs)
        return self._density_of_raw(field.density_decoder(taken.rows)[:, 0], ray, level), taken

    def density_of_taken(
        self, taken: TakenRows, index: Int[Tensor, " k"], q_density: Float[Tensor, "n d"]
    ) -> Float[Tensor, " k"]:
        """The densities of samples ``index`` of ``taken`` (``density_taken``), differentiable."""
        q, level = self.field.split_density_features(q_density)
        rows = self.density_rows.select(taken, index, q)
        return self._density_of_raw(self.field.density_decoder(rows)[:, 0], taken.ray.index_select(0, index), level)

    def direction_terms(self, directions: Float[Tensor, "n 3"]) -> Float[Tensor, "n e"]:
        """The spherical harmonics of each ray's direction (encoded once per ray)."""
        return encode_sh(directions, self.field.cfg.sh_degree)

    @torch.no_grad()
    def level_normal_cosines(
        self, points: Float[Tensor, "m 3"], ray: Int[Tensor, " m"], directions: Float[Tensor, "n 3"],
        q_density: Float[Tensor, "n d"],
    ) -> Float[Tensor, "m p"]:
        """``VisNerfField.level_normal_cosines`` (no gradient)."""
        field = self.field
        q, _ = field.split_density_features(q_density)
        probes = probe_points(points, field.cfg.level_normal_step * field.voxel_size())  # [4m, 3]
        raw = self.raw_density(field.to_grid(probes), ray.repeat_interleave(N_PROBES), q)
        return level_cosines(raw.view(-1, N_PROBES), directions.index_select(0, ray), field.cfg.level_cosine_powers)

    def color(
        self,
        points: Float[Tensor, "k 3"],
        ray: Int[Tensor, " k"],
        q_appearance: Float[Tensor, "n c"],
        ray_terms: Float[Tensor, "n e"],
        directions: Float[Tensor, "n 3"],
        q_density: Float[Tensor, "n d"],
    ) -> Float[Tensor, "k 3"]:
        """``VisNerfField.color`` at world points seen along ``directions[ray]``; ``ray_terms`` is
        ``direction_terms(directions)``."""
        field = self.field
        rows = self.appearance_rows.rows(field.to_grid(points), ray, q_appearance, tail=ray_terms)  # [k, 3c + q + e]
        parts = [rows]
        if field.facing is not None:
            feats = rows[:, : 3 * field.cfg.n_appearance_components]
            parts.append(facing_cosines(field.facing(feats), directions.index_select(0, ray)).to(rows.dtype))
        if field.levels is not None:
            parts.append(self.level_normal_cosines(points, ray, directions, q_density).to(rows.dtype))
        x = rows if len(parts) == 1 else torch.cat(parts, dim=-1)
        return torch.sigmoid(field.color_decoder(x))
