"""The ViSNeRF field: density and colour at (x, view direction, simulation parameters).

Spatial features come from two VM grids (density, appearance); parameter features from the CP
parameter axes of each branch. The ``n_param_components`` parameter features scale interleaved
groups of the spatial features (channel ``c`` by component ``c % n_param_components``) and are also
appended to the decoder input, so parameter vectors of ones leave the spatial features unchanged.

With ``FieldConfig.shading_normals`` the colour decoder's input ends with four more columns, the
shading normal and its cosine with the view direction (``normal_terms``).

Coordinates: world points are mapped to grid coordinates in [-1, 1]^3 over ``aabb``.
"""

from collections.abc import Callable

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
from visnerf.representation.param_axes import ParamAxes
from visnerf.representation.vm import VMGrid

NORMAL_TERMS = 4
"""Colour decoder input columns of the shading normal: its three components, then its cosine with
the view direction."""


def normal_terms(
    density: Callable[[Tensor], Tensor],
    points: Float[Tensor, "n 3"],
    directions: Float[Tensor, "n 3"],
    spacing: float,
) -> Float[Tensor, "n 4"]:
    """The shading normal at ``points`` and its cosine with the unit ``directions``: minus the
    gradient of ``density`` (a function of world points ``[m, 3] -> [m]``) by central differences
    ``spacing`` apart, normalised; zero where the density is flat (no division by a vanishing
    gradient). Points outward, where the density falls; a surface facing the camera has a cosine
    near -1. Not differentiated (the caller decides under which grad mode it runs)."""
    n = points.shape[0]
    offsets = torch.eye(3, dtype=points.dtype, device=points.device) * spacing  # [3, 3]
    probes = torch.cat([points[:, None, :] + offsets, points[:, None, :] - offsets], dim=1)  # [n, 6, 3]
    values = density(probes.reshape(-1, 3)).reshape(n, 2, 3).to(points.dtype)
    gradient = (values[:, 0] - values[:, 1]) / (2.0 * spacing)  # [n, 3]
    length = gradient.norm(dim=-1, keepdim=True)
    tiny = torch.finfo(points.dtype).tiny ** 0.5
    normal = torch.where(length > tiny, -gradient / length.clamp_min(tiny), torch.zeros_like(gradient))
    return torch.cat([normal, (normal * directions).sum(dim=-1, keepdim=True)], dim=-1)


def modulate(spatial: Float[Tensor, "n f"], param_feats: Float[Tensor, "n c"]) -> Float[Tensor, "n f"]:
    """Scale channel ``i`` of ``spatial`` by ``param_feats[:, i % c]``."""
    repeats = spatial.shape[1] // param_feats.shape[1]
    return spatial * param_feats.repeat(1, repeats)


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
        self.density_params = ParamAxes(cfg.param_lengths, cfg.n_param_components)
        self.appearance_params = ParamAxes(cfg.param_lengths, cfg.n_param_components)
        pc = cfg.n_param_components
        self.density_decoder = Decoder(
            3 * cfg.n_density_components + pc + positional_encoding_dim(cfg.pos_encoding_freqs),
            cfg.hidden_width,
            1,
        )
        self.color_decoder = Decoder(
            3 * cfg.n_appearance_components + pc + sh_dim(cfg.sh_degree) + NORMAL_TERMS * cfg.shading_normals,
            cfg.hidden_width,
            3,
        )

    @property
    def device(self) -> torch.device:
        return self.aabb.device

    @property
    def resolution(self) -> tuple[int, int, int]:
        return self.density_grid.resolution

    def current_config(self) -> FieldConfig:
        """The configuration that matches the current tensor shapes (after upsampling)."""
        return self.cfg.with_resolution(self.resolution)

    def normal_spacing(self) -> float:
        """Half the spacing of the central differences of ``normal_terms``: one voxel."""
        return self.voxel_size()

    def voxel_size(self) -> float:
        """Mean world-space size of one grid cell."""
        extent = self.aabb[1] - self.aabb[0]
        res = torch.tensor(self.resolution, dtype=extent.dtype, device=extent.device)
        return float((extent / (res - 1)).mean())

    def to_grid(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, "n 3"]:
        """World points -> grid coordinates in [-1, 1] (outside the box maps outside [-1, 1])."""
        extent = (self.aabb[1] - self.aabb[0]).clamp_min(torch.finfo(points.dtype).eps)
        return (points - self.aabb[0]) / extent * 2.0 - 1.0

    def param_features(
        self, params: Float[Tensor, "n k"]
    ) -> tuple[Float[Tensor, "n c"], Float[Tensor, "n c"]]:
        """(density, appearance) parameter features at normalised parameter values."""
        return self.density_params.sample(params), self.appearance_params.sample(params)

    def density_from_features(
        self, coords: Float[Tensor, "n 3"], spatial: Float[Tensor, "n f"], q: Float[Tensor, "n c"]
    ) -> Float[Tensor, " n"]:
        pe = encode_position(coords, self.cfg.pos_encoding_freqs)
        raw = self.density_decoder(torch.cat([modulate(spatial, q), q, pe], dim=-1))[:, 0]
        return F.softplus(raw + self.cfg.density_shift) * self.cfg.density_scale

    def density(self, points: Float[Tensor, "n 3"], q_density: Float[Tensor, "n c"]) -> Float[Tensor, " n"]:
        """Non-negative density (per world unit) at world points. Differentiable."""
        coords = self.to_grid(points)
        return self.density_from_features(coords, self.density_grid.sample(coords), q_density)

    def color(
        self,
        points: Float[Tensor, "n 3"],
        directions: Float[Tensor, "n 3"],
        q_appearance: Float[Tensor, "n c"],
        normals: Float[Tensor, "n 4"] | None = None,
    ) -> Float[Tensor, "n 3"]:
        """RGB in [0, 1] at world points seen along unit ``directions``. Differentiable in the
        field's parameters. With ``cfg.shading_normals``, ``normals`` are the points'
        ``shading_normals`` (required)."""
        coords = self.to_grid(points)
        spatial = self.appearance_grid.sample(coords)
        columns = [modulate(spatial, q_appearance), q_appearance, encode_sh(directions, self.cfg.sh_degree)]
        if self.cfg.shading_normals:
            if normals is None:
                raise ValueError("this field shades by surface normals: pass shading_normals(points, ...)")
            columns.append(normals.to(spatial.dtype))
        raw = self.color_decoder(torch.cat(columns, dim=-1))
        return torch.sigmoid(raw)

    def shading_normals(
        self, points: Float[Tensor, "n 3"], directions: Float[Tensor, "n 3"], q_density: Float[Tensor, "n c"]
    ) -> Float[Tensor, "n 4"]:
        """``normal_terms`` of this field's density at ``points`` (parameter features ``q_density``
        per point), without a graph: the normal is an input of the colour, not a path for its
        gradient into the density."""
        with torch.no_grad():
            q6 = q_density.repeat_interleave(6, dim=0)
            return normal_terms(lambda probes: self.density(probes, q6), points, directions, self.normal_spacing())

    @torch.no_grad()
    def set_occupancy(self, grid: Tensor | None) -> None:
        """Install (or clear) the occupancy grid used for empty-space skipping."""
        self.occupancy = None if grid is None else grid.to(device=self.device, dtype=torch.bool)

    @torch.no_grad()
    def set_param_knots(self, knots: list[Tensor]) -> None:
        """Place both branches' parameter vectors at the normalised training values."""
        for k, kn in enumerate(knots):
            self.density_params.set_knots(k, kn.to(self.device))
            self.appearance_params.set_knots(k, kn.to(self.device))

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
