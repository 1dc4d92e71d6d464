"""Priors on the factors: L1 sparsity, L1 pull of parameter vectors toward 1, total variation; and
on a level axis: the curvature of its field ``g`` and the bound on its bands' slopes."""

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from visnerf.representation.field import VisNerfField
from visnerf.representation.param_axes import ParamAxes
from visnerf.representation.vm import VMGrid
from visnerf.representation.vm_taps import MODES, grad_buffer


@dataclass(frozen=True)
class RegularizerWeights:
    l1_density: float
    param_l1: float
    tv_density: float
    tv_appearance: float
    tv_params: float


def regularization(field: VisNerfField, w: RegularizerWeights) -> dict[str, Tensor]:
    """Each weighted term (only the non-zero ones are computed)."""
    terms: dict[str, Tensor] = {}
    if w.l1_density > 0:
        terms["l1"] = w.l1_density * field.density_grid.l1()
    if w.param_l1 > 0 and field.cfg.n_params > 0:
        terms["param_l1"] = w.param_l1 * (field.density_params.l1_to_one() + field.appearance_params.l1_to_one())
    if w.tv_density > 0:
        terms["tv_density"] = w.tv_density * field.density_grid.total_variation()
    if w.tv_appearance > 0:
        terms["tv_appearance"] = w.tv_appearance * field.appearance_grid.total_variation()
    if w.tv_params > 0 and field.cfg.n_params > 0:
        terms["tv_params"] = w.tv_params * (
            field.density_params.total_variation() + field.appearance_params.total_variation()
        )
    return {k: v.to(field.device) if isinstance(v, Tensor) else torch.tensor(v) for k, v in terms.items()}


def _add_difference_terms_(values: Tensor, grad: Tensor, dim: int, scale: float) -> Tensor:
    """``mean((v[i+1] - v[i])^2)`` along ``dim`` (detached, 0-d), its gradient times ``scale`` added into ``grad``."""
    n = values.shape[dim] - 1
    if n < 1:
        return torch.zeros((), device=values.device)
    d = values.narrow(dim, 1, n) - values.narrow(dim, 0, n)  # a new contiguous tensor
    value = torch.dot(d.view(-1), d.view(-1)) / d.numel()
    d.mul_(2.0 * scale / d.numel())
    grad.narrow(dim, 1, n).add_(d)
    grad.narrow(dim, 0, n).sub_(d)
    return value


@torch.no_grad()
def add_grid_total_variation_(grid: VMGrid, weight: float) -> Tensor:
    """``weight * grid.total_variation()`` (detached), its gradient added into the factor tables'
    ``.grad`` in place: one difference tensor per term instead of autograd's graph of slices,
    powers and means, its backward and a fresh table-sized gradient added into ``.grad``."""
    planes, lines = grid.row_tables()
    plane_rows, line_rows = grid.row_views(planes, lines)
    plane_grads, line_grads = grid.row_views(grad_buffer(planes), grad_buffer(lines))
    scale = weight / len(MODES)
    total = torch.zeros((), device=planes.device)
    for rows, g in zip(plane_rows, plane_grads, strict=True):
        total = total + _add_difference_terms_(rows, g, 0, scale) + _add_difference_terms_(rows, g, 1, scale)
    for rows, g in zip(line_rows, line_grads, strict=True):
        total = total + _add_difference_terms_(rows, g, 0, scale)
    return weight * total / len(MODES)


@torch.no_grad()
def add_grid_l1_(grid: VMGrid, weight: float) -> Tensor:
    """``weight * grid.l1()`` (detached), its (sub)gradient ``sign(v)`` added into ``.grad`` in place."""
    planes, lines = grid.row_tables()
    views = grid.row_views(planes, lines)
    grads = grid.row_views(grad_buffer(planes), grad_buffer(lines))
    total = torch.zeros((), device=planes.device)
    n_factors = 2 * len(MODES)
    for part, grad in zip(views[0] + views[1], grads[0] + grads[1], strict=True):
        total = total + part.abs().sum() / part.numel()
        grad.add_(torch.sign(part), alpha=weight / (n_factors * part.numel()))
    return weight * total / n_factors


@torch.no_grad()
def add_param_priors_(field: VisNerfField, param_l1: float, tv_params: float) -> dict[str, float]:
    """The parameter-vector terms of ``regularization`` (``param_l1``, ``tv_params``: their values),
    their gradients added into the tables' ``.grad`` in closed form: ``sign(w - 1) / (T n)`` for the
    mean distance to one, ``2 d / (T' n_d)`` into ``w[i + 1]`` and out of ``w[i]`` for the mean
    squared difference ``d`` (``_add_difference_terms_``'s rule). Numpy on the tables: for a few
    hundred values, autograd's graph, or torch's operations one by one, cost many times the
    arithmetic."""
    values: dict[str, float] = {}
    if field.cfg.n_params == 0:
        return values
    axes: tuple[ParamAxes, ParamAxes] = (field.density_params, field.appearance_params)
    if param_l1 > 0:
        total = 0.0
        for module in axes:
            n_tables = len(module.tables)
            for table in module.tables:
                w, g = table.detach().numpy(), grad_buffer(table).numpy()
                offset = w - np.float32(1.0)
                total += float(np.abs(offset, dtype=np.float64).sum()) / (n_tables * w.size)
                g += np.sign(offset) * np.float32(param_l1 / (n_tables * w.size))
        values["param_l1"] = param_l1 * total
    if tv_params > 0:
        total = 0.0
        for module in axes:
            varying = [t for t in module.tables if t.shape[0] > 1]
            for table in varying:
                w, g = table.detach().numpy(), grad_buffer(table).numpy()
                d = w[1:] - w[:-1]
                total += float(np.dot(d.ravel().astype(np.float64), d.ravel())) / (len(varying) * d.size)
                d *= np.float32(2.0 * tv_params / (len(varying) * d.size))
                g[1:] += d
                g[:-1] -= d
        values["tv_params"] = tv_params * total
    return values


def backward_regularization(field: VisNerfField, w: RegularizerWeights) -> dict[str, float]:
    """Add the gradient of every weighted term of ``regularization`` into ``.grad`` and return the
    terms' values, each in place (``add_grid_l1_``, ``add_grid_total_variation_``, and, on the CPU,
    ``add_param_priors_``; elsewhere the parameter-vector terms go through autograd). Equal to
    ``sum(regularization(field, w).values()).backward()`` (tested)."""
    values: dict[str, float] = {}
    if w.l1_density > 0:
        values["l1"] = float(add_grid_l1_(field.density_grid, w.l1_density))
    if w.tv_density > 0:
        values["tv_density"] = float(add_grid_total_variation_(field.density_grid, w.tv_density))
    if w.tv_appearance > 0:
        values["tv_appearance"] = float(add_grid_total_variation_(field.appearance_grid, w.tv_appearance))
    values.update(backward_param_priors(field, w.param_l1, w.tv_params))
    return values


def backward_param_priors(field: VisNerfField, param_l1: float, tv_params: float) -> dict[str, float]:
    """The parameter-vector terms' gradients into ``.grad`` and their values: ``add_param_priors_``
    on the CPU, autograd on other devices."""
    if field.device.type == "cpu":
        return add_param_priors_(field, param_l1, tv_params)
    rest = regularization(field, RegularizerWeights(0.0, param_l1, 0.0, 0.0, tv_params))
    if rest:
        sum(rest.values()).backward()
    return {k: float(v.detach()) for k, v in rest.items()}


LEVEL_SPAN_EPS = 1e-6
"""Added to the squared span of the levels before dividing by it (a guarded division)."""


RawDensity = Callable[[Float[Tensor, "m 3"], Float[Tensor, "m c"]], Float[Tensor, " m"]]
"""The level field ``g`` at grid coordinates with per-point density features (the factors')."""


def level_curvature(
    field: VisNerfField, params: Float[Tensor, "n k"], generator: torch.Generator, step_voxels: float = 2.0,
    raw_density: RawDensity | None = None,
) -> Tensor:
    """Mean squared second difference of the level field ``g`` at ``n`` random points of the box
    along random unit directions, ``h = step_voxels`` voxels, over the squared span of the levels:
    unchanged when ``g`` and the levels are scaled together (the sharpness absorbs the scale).
    ``params``: normalised parameter values of the points (the density features of the other axes).
    0 for a field without a level axis. ``raw_density`` evaluates ``g`` (default: the field's own
    ``raw_density`` over its grid's lookups)."""
    if field.levels is None:
        return torch.zeros((), device=field.device)
    n = params.shape[0]
    lo, hi = field.aabb[0], field.aabb[1]
    x = lo + (hi - lo) * torch.rand(n, 3, generator=generator).to(field.device)  # [n, 3]
    u = torch.randn(n, 3, generator=generator).to(field.device)
    u = u / u.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    h = step_voxels * field.voxel_size()
    points = torch.cat([x - h * u, x, x + h * u])  # [3n, 3]
    q, _ = field.split_density_features(field.param_features(params)[0])
    coords = field.to_grid(points)
    if raw_density is None:
        g = field.raw_density(coords, field.density_grid.sample(coords), q.repeat(3, 1)).view(3, n)
    else:
        g = raw_density(coords, q.repeat(3, 1)).view(3, n)
    second = g[0] - 2.0 * g[1] + g[2]  # [n]
    table = field.levels.table[:, 0]
    span = table.max() - table.min()
    return second.pow(2).mean() / (span * span + LEVEL_SPAN_EPS)


def level_spacing(field: VisNerfField, max_ratio: float) -> Tensor:
    """How far a level axis's neighbouring bands differ in slope beyond ``max_ratio``: with
    ``d_i = s |level_{i+1} - level_i| / (knot_{i+1} - knot_i)`` (``s`` the sharpness, held fixed
    here, so ``d_i`` is the density logit's rise per unit of normalised isovalue across band ``i``)
    and ``r_i = log(1 + d_i)``, the mean over neighbouring bands of
    ``max(0, |r_{i+1} - r_i| - log(max_ratio))^2``: nothing while each band rises within a factor
    ``max_ratio`` of its neighbours, whatever the images make of the levels there.

    The levels are a gauge: any monotone reparameterisation of the isovalue is absorbed by ``g``,
    so the images fix them only through the surfaces. Once a training surface is opaque, its
    level's photometric gradient fades without changing sign, and Adam, which steps by about the
    learning rate whatever a gradient's size, keeps moving the level: on tangle_iso the lowest
    isovalue's level ran from about -1 to -113 in a 20-minute run (its band 190 times its
    neighbour's), every cell of the occupancy grid came to lie inside that surface (the grid's
    edge became the surface), and the values between it and the next training value rendered the
    grid as a blob (docs/decisions.md#train.level_spacing_weight). 0 with fewer than three levels
    (no neighbouring bands) and for a field without a level axis."""
    if not max_ratio > 1.0:
        raise ValueError(f"max_ratio must be > 1, got {max_ratio!r}")
    levels = field.levels
    if levels is None or levels.table.shape[0] < 3:
        return torch.zeros((), device=field.device)
    table = levels.table[:, 0]  # [m]
    knots = levels.knots  # [m], strictly increasing (LevelAxis.set_knots)
    slope = (table[1:] - table[:-1]).abs() / (knots[1:] - knots[:-1])  # [m - 1]
    rise = torch.log1p(levels.sharpness().detach() * slope)  # [m - 1]
    excess = ((rise[1:] - rise[:-1]).abs() - math.log(max_ratio)).clamp_min(0.0)  # [m - 2]
    return excess.pow(2).mean()


@dataclass(frozen=True)
class LevelPriorWeights:
    """A level axis's priors (``TrainConfig.level_*``); a weight of 0 leaves its prior out."""

    curvature: float
    curvature_points: int
    """Rays of the batch at whose parameter values the curvature is taken."""
    spacing: float
    spacing_ratio: float


def backward_level_priors(field: VisNerfField, params: Float[Tensor, "n k"], w: LevelPriorWeights,
                          generator: torch.Generator, raw_density: RawDensity | None = None) -> dict[str, float]:
    """A level axis's curvature and spacing priors back-propagated into ``.grad``; their values (none
    for a field without a level axis). The curvature is taken at the parameter values of random
    rays of the batch (the other axes' density features); ``raw_density``: the fused step's."""
    terms: dict[str, float] = {}
    if field.levels is None:
        return terms
    if w.curvature > 0:
        pick = torch.randint(0, params.shape[0], (w.curvature_points,), generator=generator)
        picked = params[pick.to(params.device)]
        curvature = w.curvature * level_curvature(field, picked, generator, raw_density=raw_density)
        curvature.backward()
        terms["level_curvature"] = float(curvature.detach())
    if w.spacing > 0:
        spacing = w.spacing * level_spacing(field, w.spacing_ratio)
        if spacing.requires_grad:  # fewer than three levels: no neighbouring bands to hold
            spacing.backward()
            terms["level_spacing"] = float(spacing.detach())
    return terms

