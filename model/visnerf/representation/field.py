"""The ViSNeRF field: density and colour at (x, view direction, simulation parameters).

Spatial features come from two VM grids (density, appearance); parameter features from the CP
parameter axes of each branch. The ``n_param_components`` parameter features scale interleaved
groups of the spatial features (channel ``c`` by component ``c % n_param_components``) and are also
appended to the decoder input, so parameter vectors of ones leave the spatial features unchanged.

A level axis (``FieldConfig.level_set_axis``, an isovalue sweep) takes no density factors: the
density is ``softplus(s (g(x) - level(v)) + shift) * scale`` with ``g`` the density decoder's output
and ``level`` and ``s`` learnt (``param_axes.LevelAxis``), so every isovalue's surface is a level
set of one field ``g``. Its colour decoder also reads the cosine between ``g``'s gradient (the
surface normal, from four probes around the sample) and the view, which holds between the
training isovalues where the appearance features were never fitted.

Coordinates: world points are mapped to grid coordinates in [-1, 1]^3 over ``aabb``.
"""

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from visnerf.config import FieldConfig
from visnerf.representation.decoders import (
    Decoder,
    encode_position,
    encode_sh,
    positional_encoding_dim,
    sh_dim,
)
from visnerf.representation.param_axes import LevelAxis, ParamAxes
from visnerf.representation.vm import VMGrid


def modulate(spatial: Float[Tensor, "n f"], param_feats: Float[Tensor, "n c"]) -> Float[Tensor, "n f"]:
    """Scale channel ``i`` of ``spatial`` by ``param_feats[:, i % c]``."""
    repeats = spatial.shape[1] // param_feats.shape[1]
    return spatial * param_feats.repeat(1, repeats)


def facing_cosines(vectors: Float[Tensor, "n v"], directions: Float[Tensor, "n 3"]) -> Float[Tensor, "n m"]:
    """Cosine between each of the ``m = v / 3`` learnt vectors of a point and its unit view
    direction (float32; a vector of length zero gives 0)."""
    n = vectors.shape[0]
    u = vectors.float().view(n, -1, 3)  # [n, m, 3]
    length = torch.sqrt(u.pow(2).sum(-1) + FACING_EPS)  # [n, m], never 0
    return (u * directions.float()[:, None, :]).sum(-1) / length


FACING_EPS = 1e-12
"""Added to a learnt vector's squared length before its root (a guarded division)."""
TETRAHEDRON = ((1.0, 1.0, 1.0), (1.0, -1.0, -1.0), (-1.0, 1.0, -1.0), (-1.0, -1.0, 1.0))
"""Probe directions of the gradient: ``sum_i v_i g(x + h v_i) / 4h`` is the gradient to second
order in ``h``, like central differences, from four values of ``g`` instead of six."""
N_PROBES = len(TETRAHEDRON)


def level_cosines(
    raw_probes: Float[Tensor, "n 4"], directions: Float[Tensor, "n 3"], powers: tuple[int, ...] = ()
) -> Float[Tensor, "n p"]:
    """Cosine between the gradient of the level field ``g`` and the unit view direction, from ``g``
    at the probes of ``probe_points``, then each of ``powers`` of its positive part (``p = 1 +
    len(powers)`` columns). ``g`` grows inwards, so the cosine is that of the outward normal with
    the direction to the eye: positive on the side of a surface facing the camera. A flat ``g``
    gives 0 (guarded division)."""
    vertices = torch.tensor(TETRAHEDRON, device=raw_probes.device)  # [4, 3]
    grad = raw_probes.float() @ vertices  # [n, 3], 4h times the gradient
    length = torch.sqrt(grad.pow(2).sum(-1, keepdim=True) + FACING_EPS)
    cosine = (grad * directions.float()).sum(-1, keepdim=True) / length  # [n, 1]
    if not powers:
        return cosine
    facing = cosine.clamp(0.0, 1.0)  # a rounding past 1 must not grow under a high power
    return torch.cat([cosine, *(facing.pow(k) for k in powers)], dim=-1)


def probe_points(points: Float[Tensor, "n 3"], step: float) -> Float[Tensor, "n4 3"]:
    """``x + h v_i`` for the ``TETRAHEDRON`` directions ``v_i``: ``[4n, 3]``, four rows a point."""
    offsets = step * torch.tensor(TETRAHEDRON, dtype=points.dtype, device=points.device)  # [4, 3]
    return (points[:, None, :] + offsets).reshape(-1, 3)


class VisNerfField(nn.Module):
    """Density and colour of a parameterised scene. Buffers: ``aabb`` [2, 3] (world box)."""

    def __init__(self, cfg: FieldConfig, aabb: Float[Tensor, "2 3"]) -> None:
        super().__init__()
        self.cfg = cfg
        self.register_buffer("aabb", aabb.detach().clone().float())
        self.occupancy: Tensor | None
        self.register_buffer("occupancy", None)  # bool [x, y, z] over aabb, set after training warm-up
        self.density_grid = VMGrid(cfg.n_density_components, cfg.resolution, cfg.init_scale)
        self.appearance_grid = VMGrid(cfg.n_appearance_components, cfg.resolution, cfg.init_scale)
        axis = cfg.level_set_axis
        if axis >= cfg.n_params:
            raise ValueError(f"level_set_axis {axis} names no parameter axis: the field has {cfg.n_params}")
        density_lengths = tuple(n for k, n in enumerate(cfg.param_lengths) if k != axis)
        self.density_params = ParamAxes(density_lengths, cfg.n_param_components)
        self.levels: LevelAxis | None = None if axis < 0 else LevelAxis(cfg.param_lengths[axis])
        self.appearance_params = ParamAxes(cfg.param_lengths, cfg.n_param_components)
        pc = cfg.n_param_components
        self.density_decoder = Decoder(
            3 * cfg.n_density_components + pc + positional_encoding_dim(cfg.pos_encoding_freqs),
            cfg.hidden_width,
            1,
        )
        self.color_decoder = Decoder(
            3 * cfg.n_appearance_components + pc + sh_dim(cfg.sh_degree) + cfg.facing_vectors
            + (1 + len(cfg.level_cosine_powers) if self.levels is not None else 0), cfg.hidden_width, 3
        )
        self.facing: nn.Linear | None = None
        if cfg.facing_vectors > 0:
            self.facing = nn.Linear(3 * cfg.n_appearance_components, 3 * cfg.facing_vectors, bias=False)

    @property
    def device(self) -> torch.device:
        return self.aabb.device

    @property
    def resolution(self) -> tuple[int, int, int]:
        return self.density_grid.resolution

    def current_config(self) -> FieldConfig:
        """The configuration that matches the current tensor shapes (after upsampling)."""
        return self.cfg.with_resolution(self.resolution)

    def voxel_size(self) -> float:
        """Mean world-space size of one grid cell."""
        extent = self.aabb[1] - self.aabb[0]
        res = torch.tensor(self.resolution, dtype=extent.dtype, device=extent.device)
        return float((extent / (res - 1)).mean())

    def grid_extent(self, dtype: torch.dtype) -> Float[Tensor, " 3"]:
        """The box's size per axis, at least ``dtype``'s epsilon (``to_grid`` divides by it)."""
        return (self.aabb[1] - self.aabb[0]).clamp_min(torch.finfo(dtype).eps)

    def to_grid(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, "n 3"]:
        """World points -> grid coordinates in [-1, 1] (outside the box maps outside [-1, 1])."""
        return (points - self.aabb[0]) / self.grid_extent(points.dtype) * 2.0 - 1.0

    def param_features(
        self, params: Float[Tensor, "n k"]
    ) -> tuple[Float[Tensor, "n d"], Float[Tensor, "n c"]]:
        """(density, appearance) parameter features at normalised parameter values. With a level
        axis the density features carry the level as a last column (``split_density_features``)."""
        axis = self.cfg.level_set_axis
        if self.levels is None:
            return self.density_params.sample(params), self.appearance_params.sample(params)
        others = torch.cat([params[:, :axis], params[:, axis + 1:]], dim=1)  # [n, k-1]
        q_density = torch.cat([self.density_params.sample(others), self.levels.sample(params[:, axis])[:, None]], dim=1)
        return q_density, self.appearance_params.sample(params)

    def split_density_features(
        self, q: Float[Tensor, "n d"]
    ) -> tuple[Float[Tensor, "n c"], Float[Tensor, " n"] | None]:
        """Density features ``q`` as (the factors' features, the level or None)."""
        if self.levels is None:
            return q, None
        return q[:, :-1], q[:, -1]

    def raw_density(
        self, coords: Float[Tensor, "n 3"], spatial: Float[Tensor, "n f"], q: Float[Tensor, "n c"]
    ) -> Float[Tensor, " n"]:
        """The density decoder's output at the factors' features ``q`` (a level axis's ``g``)."""
        pe = encode_position(coords, self.cfg.pos_encoding_freqs)
        return self.density_decoder(torch.cat([modulate(spatial, q), q, pe], dim=-1))[:, 0]

    def density_from_features(
        self, coords: Float[Tensor, "n 3"], spatial: Float[Tensor, "n f"], q: Float[Tensor, "n d"]
    ) -> Float[Tensor, " n"]:
        q, level = self.split_density_features(q)
        raw = self.raw_density(coords, spatial, q)
        if level is not None and self.levels is not None:
            raw = (raw - level) * self.levels.sharpness()
        return F.softplus(raw + self.cfg.density_shift) * self.cfg.density_scale

    def density(self, points: Float[Tensor, "n 3"], q_density: Float[Tensor, "n d"]) -> Float[Tensor, " n"]:
        """Non-negative density (per world unit) at world points. Differentiable."""
        coords = self.to_grid(points)
        return self.density_from_features(coords, self.density_grid.sample(coords), q_density)

    @torch.no_grad()
    def level_normal_cosines(
        self, points: Float[Tensor, "n 3"], directions: Float[Tensor, "n 3"], q_density: Float[Tensor, "n d"]
    ) -> Float[Tensor, "n p"]:
        """``level_cosines`` of the level field ``g`` at ``points`` (probes
        ``cfg.level_normal_step`` voxels away along each axis). No gradient: the shading reads the
        shape, it does not move it."""
        q, _ = self.split_density_features(q_density)
        probes = probe_points(points, self.cfg.level_normal_step * self.voxel_size())  # [4n, 3]
        coords = self.to_grid(probes)
        raw = self.raw_density(coords, self.density_grid.sample(coords), q.repeat_interleave(N_PROBES, dim=0))
        return level_cosines(raw.view(-1, N_PROBES), directions, self.cfg.level_cosine_powers)

    def color(
        self,
        points: Float[Tensor, "n 3"],
        directions: Float[Tensor, "n 3"],
        q_appearance: Float[Tensor, "n c"],
        q_density: Float[Tensor, "n d"] | None = None,
    ) -> Float[Tensor, "n 3"]:
        """RGB in [0, 1] at world points seen along unit ``directions``. Differentiable. A field
        with a level axis also reads the cosine of its level field's normal with the view, for
        which it needs the density features ``q_density`` of the points."""
        coords = self.to_grid(points)
        spatial = self.appearance_grid.sample(coords)
        sh = encode_sh(directions, self.cfg.sh_degree)
        feats = modulate(spatial, q_appearance)
        parts = [feats, q_appearance, sh]
        if self.facing is not None:
            parts.append(facing_cosines(self.facing(feats), directions))
        if self.levels is not None:
            if q_density is None:
                raise ValueError("a field with a level axis needs the density features for its colour")
            parts.append(self.level_normal_cosines(points, directions, q_density).to(feats.dtype))
        raw = self.color_decoder(torch.cat(parts, dim=-1))
        return torch.sigmoid(raw)

    @torch.no_grad()
    def set_occupancy(self, grid: Tensor | None) -> None:
        """Install (or clear) the occupancy grid used for empty-space skipping."""
        self.occupancy = None if grid is None else grid.to(device=self.device, dtype=torch.bool)

    @torch.no_grad()
    def set_param_knots(self, knots: list[Tensor]) -> None:
        """Place both branches' parameter vectors at the normalised training values."""
        axis = self.cfg.level_set_axis
        for k, kn in enumerate(knots):
            self.appearance_params.set_knots(k, kn.to(self.device))
            if k == axis and self.levels is not None:
                self.levels.set_knots(kn.to(self.device))
            else:
                self.density_params.set_knots(k if axis < 0 or k < axis else k - 1, kn.to(self.device))

    @torch.no_grad()
    def resample(self, resolution: tuple[int, int, int], new_aabb: Tensor | None = None) -> None:
        """Upsample the grids and/or shrink them to ``new_aabb``; the optimizer must be rebuilt."""
        lower = upper = None
        if new_aabb is not None:
            lower = self.to_grid(new_aabb[0:1])[0]
            upper = self.to_grid(new_aabb[1:2])[0]
        self.density_grid.resample(resolution, lower, upper)
        self.appearance_grid.resample(resolution, lower, upper)
        if new_aabb is not None:
            self.aabb.copy_(new_aabb)
            self.occupancy = None  # its cells referred to the old box
