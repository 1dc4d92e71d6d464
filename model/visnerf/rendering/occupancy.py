"""Occupancy grid: which cells of the box can hold content, for empty-space skipping.

The grid is the union over the parameter space: a cell is occupied when the density somewhere in
it (the centres of its sub-cells) is visible at ANY of the evaluated parameter settings (all
training settings, or a capped subset that always includes the corners of the parameter box),
then dilated by one cell (``dilation``: cells that content may grow into while training samples
only the grid; a training grid rebuilt late, once content has formed, can leave it out).
"""

import itertools

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float
from torch import Tensor

from visnerf.representation.field import VisNerfField
from visnerf.representation.frame_field import FrameField
from visnerf.runtime import bf16_native


def query_occupancy(
    grid: Bool[Tensor, "x y z"], aabb: Float[Tensor, "2 3"], points: Float[Tensor, "n 3"]
) -> Bool[Tensor, " n"]:
    """Occupancy of the cells holding ``points``; points outside the box are empty."""
    res = torch.tensor(grid.shape, device=points.device, dtype=points.dtype)
    rel = (points - aabb[0]) / (aabb[1] - aabb[0]).clamp_min(torch.finfo(points.dtype).eps)  # [n, 3]
    inside = ((rel >= 0) & (rel <= 1)).all(dim=-1)
    idx = (rel * res).long().clamp(min=0)
    idx = torch.minimum(idx, (res - 1).long())
    flat = (idx[:, 0] * grid.shape[1] + idx[:, 1]) * grid.shape[2] + idx[:, 2]
    return inside & grid.reshape(-1)[flat]


def cell_centres(aabb: Float[Tensor, "2 3"], resolution: tuple[int, int, int]) -> Float[Tensor, "x y z 3"]:
    axes = [
        aabb[0, i] + (torch.arange(r, device=aabb.device, dtype=aabb.dtype) + 0.5) / r * (aabb[1, i] - aabb[0, i])
        for i, r in enumerate(resolution)
    ]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)


def parameter_settings(
    knots: list[Float[Tensor, " m"]], max_settings: int, generator: torch.Generator | None = None
) -> Float[Tensor, "s k"]:
    """Normalised parameter settings to evaluate: all knot combinations, or the corners plus a
    random subset when there are more than ``max_settings``. ``[1, 0]`` for K = 0."""
    if not knots:
        return torch.zeros(1, 0)
    combos = torch.tensor(list(itertools.product(*[k.tolist() for k in knots])), dtype=torch.float32)
    if combos.shape[0] <= max_settings:
        return combos
    corners = torch.tensor(list(itertools.product(*[[k[0].item(), k[-1].item()] for k in knots])))
    perm = torch.randperm(combos.shape[0], generator=generator)[: max(0, max_settings - corners.shape[0])]
    return torch.cat([corners.float(), combos[perm]], dim=0)


def cell_offsets(resolution: tuple[int, int, int], extent: Float[Tensor, " 3"], per_axis: int) -> Float[Tensor, "p 3"]:
    """World offsets from a cell's centre of the centres of its ``per_axis``^3 sub-cells."""
    frac = (torch.arange(per_axis, dtype=extent.dtype, device=extent.device) + 0.5) / per_axis - 0.5
    cell = extent / torch.tensor(resolution, dtype=extent.dtype, device=extent.device)
    grid = torch.stack(torch.meshgrid(frac, frac, frac, indexing="ij"), dim=-1).reshape(-1, 3)
    return grid * cell


@torch.no_grad()
def build_occupancy(
    field: VisNerfField,
    resolution: tuple[int, int, int],
    settings: Float[Tensor, "s k"],
    step: float,
    threshold: float,
    candidates: Bool[Tensor, "x y z"] | None = None,
    chunk: int = 65536,
    samples_per_axis: int = 2,
    dilation: int = 1,
) -> Bool[Tensor, "x y z"]:
    """Union over ``settings`` of ``max alpha over the cell > threshold``, dilated by ``dilation``
    cells (a cube of side ``2 * dilation + 1`` around each occupied cell; 0: none).

    Each setting evaluates only the cells no setting before it found occupied (the union does not
    depend on the order): where content is much the same at every setting, as in a parameter sweep
    of one simulation, the first setting finds most occupied cells and the others evaluate what is
    left. A 96^3 rebuild of a cosmo_sim field at 27 settings took 63 s of a 10-minute training
    budget when every setting evaluated every cell (docs/decisions.md#frames.setting_grids).

    Alpha is taken at the centres of ``samples_per_axis``^3 sub-cells of every cell: a structure
    thinner than a cell (a sharp isosurface, a filament) that passes between cell centres is still
    seen (tested with a shell a tenth of a cell thick). Only ``candidates`` cells are evaluated
    when given (the rest count as empty before dilation). Densities come from the inference path
    (``FrameField``, bf16 products where the device has bf16 units: the rounding, a few parts in
    1e3 of sigma, does not matter against a threshold on alpha of 1e-4).
    """
    if dilation < 0:  # before the evaluation, not after it
        raise ValueError(f"dilation must be >= 0 cells, got {dilation}")
    all_pts = cell_centres(field.aabb, resolution).reshape(-1, 3)  # [x*y*z, 3]
    cand = (
        torch.arange(all_pts.shape[0], device=all_pts.device)
        if candidates is None
        else candidates.reshape(-1).nonzero()[:, 0].to(all_pts.device)
    )
    pts = all_pts[cand]
    offsets = cell_offsets(resolution, field.aabb[1] - field.aabb[0], samples_per_axis)  # [p, 3]
    per_chunk = max(1, chunk // offsets.shape[0])
    occupied = torch.zeros(pts.shape[0], dtype=torch.bool, device=pts.device)
    settings = settings.to(pts.device)
    for setting in settings:
        # a union: a cell some earlier setting found occupied stays so, whatever this one says
        open_cells = (~occupied).nonzero()[:, 0]  # [o], indices into pts
        if open_cells.numel() == 0:
            break
        q_d, q_a = field.param_features(setting[None])
        frame = FrameField(field, q_d, q_a, torch.bfloat16 if bf16_native(pts.device) else torch.float32)
        for start in range(0, open_cells.numel(), per_chunk):
            cells = open_cells[start : start + per_chunk]  # [c]
            part = (pts[cells, None, :] + offsets[None]).reshape(-1, 3)  # [c * p, 3]
            sigma = frame.density(part).reshape(-1, offsets.shape[0]).amax(dim=1)
            alpha = -torch.expm1(-sigma * step)
            occupied[cells] |= alpha > threshold
    full = torch.zeros(all_pts.shape[0], dtype=torch.bool, device=all_pts.device)
    full[cand] = occupied
    return dilate(full.reshape(resolution), dilation)


def dilate(grid: Bool[Tensor, "x y z"], cells: int) -> Bool[Tensor, "x y z"]:
    """``grid`` grown by ``cells`` in every direction (max over a cube of side ``2 * cells + 1``)."""
    if cells < 0:
        raise ValueError(f"dilation must be >= 0 cells, got {cells}")
    if cells == 0:
        return grid.clone()
    pooled = F.max_pool3d(grid.float()[None, None], kernel_size=2 * cells + 1, stride=1, padding=cells)
    return pooled[0, 0] > 0


def occupied_bounds(
    grid: Bool[Tensor, "x y z"], aabb: Float[Tensor, "2 3"]
) -> Float[Tensor, "2 3"] | None:
    """World box of the occupied cells (None if nothing is occupied)."""
    idx = grid.nonzero()
    if idx.numel() == 0:
        return None
    res = torch.tensor(grid.shape, device=aabb.device, dtype=aabb.dtype)
    lo = idx.amin(0).to(aabb.dtype) / res
    hi = (idx.amax(0).to(aabb.dtype) + 1) / res
    extent = aabb[1] - aabb[0]
    return torch.stack([aabb[0] + lo * extent, aabb[0] + hi * extent])
