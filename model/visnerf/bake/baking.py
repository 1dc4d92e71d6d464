"""Bake one parameter setting of a model: the field at the vertices of a grid over the setting's
occupied cells, its colour fitted per vertex as a function of the view (docs/decisions.md#bake.shading).

What is baked is what comes before each nonlinearity, so that interpolation between vertices
draws what the model draws: the softplus's argument (a sharpened level field, for an
isosurface, is interpolated and then sharpened, not the other way round), and the colour
decoder's logits before their sigmoid, least-squares fitted per vertex over view directions on
the basis the header names (``bake_file.BakeHeader.shading``). The field answers through
``BakeSource``: the bake never reads the field's layout.
"""

import hashlib
import math
import time
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float
from torch import Tensor

from visnerf.bake.bake_file import DENSITY_FILL, Bake, BakeError, BakeHeader, Shading, basis_size
from visnerf.config.bake import BakeConfig
from visnerf.representation.decoders import encode_sh
from visnerf.representation.field import TETRAHEDRON, level_cosines

RAW_LIMIT = 60000.0
"""Largest raw density stored (float16 reaches 65504); its activation is far past opaque."""
POINTS_A_PASS = 4096
"""Vertices whose colour is fitted at once: their logits at every direction stay within tens of MB."""


@runtime_checkable
class BakeSource(Protocol):
    """The field at one setting, as a bake reads it."""

    @property
    def density_activation(self) -> tuple[float, float]:
        """(shift, scale): density = ``softplus(raw + shift) * scale``."""
        ...

    @property
    def level_step(self) -> float | None:
        """World distance of a normal's probes; None: the colour reads no normal (``sh`` shading)."""
        ...

    def raw_density(self, points: Float[Tensor, "m 3"]) -> Float[Tensor, " m"]: ...

    def level_probes(self, points: Float[Tensor, "m 3"]) -> Float[Tensor, "m 4"]: ...

    def view_logits(self, points: Float[Tensor, "m 3"], directions: Float[Tensor, "m v 3"],
                    probes: Float[Tensor, "m 4"] | None = None) -> Float[Tensor, "m v 3"]: ...


@dataclass(frozen=True)
class BakeTarget:
    """What the bake needs of the scene besides its field: the box, the grid, the renderer's
    spacing and thresholds, the setting's name and values."""

    aabb: tuple[tuple[float, float, float], tuple[float, float, float]]
    model_grid: tuple[int, int, int]
    step: float
    """Sample spacing of the model's full frames, world units; the bake keeps it."""
    occupancy_threshold: float
    early_stop_eps: float
    union: Bool[Tensor, "x y z"] | None
    """The model's occupancy grid (cells over ``aabb``, its own resolution) or None: everywhere."""
    cosine_powers: tuple[int, ...]
    background: tuple[float, float, float]
    kind: str
    title: str
    params: dict[str, float]
    source: dict[str, str]


def fibonacci_directions(n: int) -> Float[Tensor, "n 3"]:
    """``n`` unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    k = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * k / n
    r = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1).float()


def colour_basis(
    shading: Shading, sh_degree: int, directions: Float[Tensor, "n 3"],
    probes: Float[Tensor, "n 4"] | None, powers: tuple[int, ...],
) -> Float[Tensor, "n b"]:
    """The basis a vertex's logits are a sum of, at unit ``directions``: spherical harmonics of
    degree ``sh_degree``; for ``level`` also the level cosines of ``probes`` (``level_cosines``)."""
    sh = encode_sh(directions, sh_degree)
    if shading == "sh":
        return sh
    if probes is None:
        raise ValueError("level shading needs the probes of the level field")
    return torch.cat([sh, level_cosines(probes, directions, powers)], dim=-1)


def _vertex_axes(target: BakeTarget, grid: tuple[int, int, int]) -> list[Tensor]:
    lo, hi = target.aabb
    return [torch.linspace(lo[i], hi[i], grid[i], dtype=torch.float64).float() for i in range(3)]


def _union_cells(target: BakeTarget, grid: tuple[int, int, int]) -> Bool[Tensor, "z y x"]:
    """Bake cells whose centre lies in a cell of the model's grid, dilated by a cell."""
    cells = tuple(n - 1 for n in grid)
    if target.union is None:
        return torch.ones(cells[2], cells[1], cells[0], dtype=torch.bool)
    union = target.union.cpu()
    index = []
    for axis in range(3):  # the union cell of each bake cell's centre, per axis
        centre = (torch.arange(cells[axis], dtype=torch.float64) + 0.5) / cells[axis]
        index.append((centre * union.shape[axis]).long().clamp(0, union.shape[axis] - 1))
    inside = union[index[0][:, None, None], index[1][None, :, None], index[2][None, None, :]]  # [x, y, z]
    return _dilate(inside.permute(2, 1, 0).contiguous())


def _dilate(cells: Bool[Tensor, "z y x"], reach: int = 1) -> Bool[Tensor, "z y x"]:
    """Cells within ``reach`` cells of a given one along each axis (a cube around each)."""
    out = cells
    for axis in range(3):
        grown = out.clone()
        n = out.shape[axis]
        for k in range(1, min(reach, n - 1) + 1):
            grown.narrow(axis, k, n - k).logical_or_(out.narrow(axis, 0, n - k))
            grown.narrow(axis, 0, n - k).logical_or_(out.narrow(axis, k, n - k))
        out = grown
    return out


def _cell_vertices(cells: Bool[Tensor, "z y x"]) -> Bool[Tensor, "z1 y1 x1"]:
    """Vertices of the given cells (a cell reads its eight corners)."""
    out = cells
    for axis in range(3):
        shape = list(out.shape)
        shape[axis] += 1
        grown = torch.zeros(shape, dtype=torch.bool)
        n = out.shape[axis]
        grown.narrow(axis, 0, n).logical_or_(out)
        grown.narrow(axis, 1, n).logical_or_(out)
        out = grown
    return out


def _cell_max(values: Float[Tensor, "z1 y1 x1"]) -> Float[Tensor, "z y x"]:
    """The largest of each cell's eight corner values."""
    out = values
    for axis in range(3):
        n = out.shape[axis]
        out = torch.maximum(out.narrow(axis, 0, n - 1), out.narrow(axis, 1, n - 1))
    return out


def bake_grid(model_grid: tuple[int, int, int], cfg: BakeConfig) -> tuple[int, int, int]:
    """Vertices along x, y, z: the model's grid times ``grid_scale`` (docs/decisions.md#bake.grid)."""
    grid = tuple(max(2, round((n - 1) * cfg.grid_scale) + 1) for n in model_grid)
    if math.prod(grid) > cfg.max_vertices:
        raise BakeError(f"a bake grid of {grid} vertices is larger than {cfg.max_vertices}")
    return grid  # type: ignore[return-value]


@torch.no_grad()
def bake_setting(source: BakeSource, target: BakeTarget, cfg: BakeConfig | None = None) -> Bake:
    """The bake of one setting (CPU tensors in, numpy arrays out); ``cfg`` None: ``BakeConfig()``."""
    cfg = cfg or BakeConfig()
    t0 = time.perf_counter()
    grid = bake_grid(target.model_grid, cfg)
    nx, ny, nz = grid
    axes = _vertex_axes(target, grid)
    shift, scale = source.density_activation
    candidates = _union_cells(target, grid)  # [nz-1, ny-1, nx-1]
    cand_vertices = _cell_vertices(candidates)  # [nz, ny, nx]
    raw = torch.full((nz, ny, nx), DENSITY_FILL, dtype=torch.float32)
    index = cand_vertices.nonzero()  # [m, 3] as z, y, x
    points = _points(axes, index)
    if len(points):  # the softplus's whole argument: a level far from 0 must not meet the fill
        raw[cand_vertices] = source.raw_density(points) + shift
    alpha = -torch.expm1(-F.softplus(raw) * scale * target.step)
    visible = (_cell_max(alpha) > target.occupancy_threshold) & candidates
    occupied = _dilate(visible) & candidates
    needed = _cell_vertices(occupied)
    coloured = _cell_vertices(visible)  # a sample in the dilation's cells weighs under the threshold
    stored = needed
    if source.level_step is not None:  # a normal's probes reach past the cell: their vertices too
        lo, hi = target.aabb
        spacing = min((hi[i] - lo[i]) / (grid[i] - 1) for i in range(3))
        reach = math.ceil(source.level_step / spacing)
        stored = _dilate(needed, reach)
        more = stored & ~cand_vertices
        if more.any():
            raw[more] = source.raw_density(_points(axes, more.nonzero())) + shift
    raw[~stored] = DENSITY_FILL
    raw.clamp_(DENSITY_FILL, RAW_LIMIT)  # float16 holds it
    shading: Shading = "sh" if source.level_step is None else "level"
    powers = target.cosine_powers if shading == "level" else ()
    colour_points = _points(axes, coloured.nonzero())
    sh_degree, choice = choose_sh_degree(source, colour_points, shading, powers, cfg)
    n_basis = basis_size(shading, sh_degree, powers)
    coefficients = torch.zeros(nz, ny, nx, 3 * n_basis)
    coefficients[coloured] = _fit_colours(source, colour_points, shading, sh_degree, powers, cfg)[0]
    header = BakeHeader(
        shading=shading, sh_degree=sh_degree, cosine_powers=tuple(powers), grid=grid, brick=cfg.brick,
        aabb=target.aabb, density_scale=float(scale), step=target.step,
        normal_step=source.level_step, early_stop_eps=target.early_stop_eps, background=target.background,
        kind=target.kind, title=target.title, params=dict(target.params),
        source={**target.source, "grid_scale": f"{cfg.grid_scale:g}", "sh_degree": choice,
                "seconds": f"{time.perf_counter() - t0:.3f}"},
    )
    return _bricks(header, raw, coefficients, coloured, stored, occupied)


def _points(axes: list[Tensor], index: Tensor) -> Float[Tensor, "m 3"]:
    """World points of vertex indices ``[m, 3]`` (z, y, x)."""
    return torch.stack([axes[0][index[:, 2]], axes[1][index[:, 1]], axes[2][index[:, 0]]], dim=-1)


def choose_sh_degree(
    source: BakeSource, points: Float[Tensor, "m 3"], shading: Shading, powers: tuple[int, ...], cfg: BakeConfig,
) -> tuple[int, str]:
    """(the lowest degree up to ``cfg.max_sh_degree`` whose fit leaves at most
    ``cfg.sh_tolerance`` levels of RMS colour error on an even sample of ``points``, the reason)."""
    sample = points[:: max(1, points.shape[0] // cfg.sh_sample)]
    views = cfg.directions_per_basis * basis_size(shading, cfg.max_sh_degree, powers)  # the same for every degree
    errors = [_fit_colours(source, sample, shading, k, powers, cfg, views)[1] for k in range(cfg.max_sh_degree + 1)]
    chosen = next(k for k, e in enumerate(errors) if e <= errors[-1] + cfg.sh_tolerance)
    measured = ", ".join(f"degree {k}: {e:.2f}" for k, e in enumerate(errors))
    return chosen, (f"degree {chosen}: RMS colour error of the fit on {sample.shape[0]} vertices and {views} views, "
                    f"levels of 255 ({measured}; a degree is taken when within {cfg.sh_tolerance:g} of the highest)")


def _fit_colours(
    source: BakeSource, points: Float[Tensor, "m 3"], shading: Shading, sh_degree: int,
    powers: tuple[int, ...], cfg: BakeConfig, views: int = 0,
) -> tuple[Float[Tensor, "m c"], float]:
    """(per vertex, the least-squares coefficients (ridge ``cfg.ridge``) of its clipped logits
    over view directions, the fit's RMS colour error in levels of 255): an even spread of
    directions, and for ``level`` shading also directions around the level field's normal, where
    its powers rise to a highlight. ``views``: directions in the even spread (0:
    ``cfg.directions_per_basis`` a basis function)."""
    n_basis = basis_size(shading, sh_degree, powers)
    directions = fibonacci_directions(views or cfg.directions_per_basis * n_basis)  # [v, 3]
    out = torch.empty(points.shape[0], 3 * n_basis)
    squared, count = 0.0, 0
    for start in range(0, points.shape[0], POINTS_A_PASS):
        p = points[start:start + POINTS_A_PASS]
        m = p.shape[0]
        dirs = directions[None].expand(m, -1, -1)
        probes = None
        if shading == "level":
            probes = source.level_probes(p)  # [m, 4]
            dirs = torch.cat([dirs, _around_normal(probes)], dim=1)
        v = dirs.shape[1]
        logits = source.view_logits(p, dirs, probes).clamp(-cfg.logit_clip, cfg.logit_clip)  # [m, v, 3]
        flat = dirs.reshape(m * v, 3)
        basis = colour_basis(shading, sh_degree, flat, None if probes is None else probes.repeat_interleave(v, 0),
                             powers).view(m, v, n_basis)
        gram = basis.transpose(1, 2) @ basis + cfg.ridge * torch.eye(n_basis)  # [m, b, b]
        coef = torch.linalg.solve(gram, basis.transpose(1, 2) @ logits)  # [m, b, 3]
        out[start:start + m] = coef.reshape(m, 3 * n_basis)
        fitted = torch.sigmoid(basis @ coef) - torch.sigmoid(logits)  # [m, v, 3]
        squared += float(fitted.pow(2).sum()) * 255.0**2
        count += fitted.numel()
    return out, math.sqrt(squared / max(count, 1))


NORMAL_OFFSETS = (0.0, 0.1, 0.2, 0.35)
"""Tangent offsets of the directions fitted around a normal: cosines 1, 0.995, 0.98 and 0.94, in
two tangent directions each past the first."""


def _around_normal(probes: Float[Tensor, "m 4"]) -> Float[Tensor, "m k 3"]:
    """Unit directions near the level field's gradient (``level_cosines`` is 1 along it)."""
    grad = probes.float() @ torch.tensor(TETRAHEDRON)  # [m, 3]
    n = grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    helper = torch.where(n[:, :1].abs() < 0.9, torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([[0.0, 1.0, 0.0]]))
    t1 = torch.linalg.cross(n, helper)
    t1 = t1 / t1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    t2 = torch.linalg.cross(n, t1)
    dirs = [n]
    for k, e in enumerate(NORMAL_OFFSETS[1:]):
        for t in ((t1, t2) if k % 2 == 0 else (t2, -t1)):
            dirs.append(n + e * t)
    stacked = torch.stack(dirs, dim=1)
    return stacked / stacked.norm(dim=-1, keepdim=True)


def _bricks(
    header: BakeHeader, raw: Float[Tensor, "z y x"], coefficients: Float[Tensor, "z y x c"],
    needed: Bool[Tensor, "z y x"], stored: Bool[Tensor, "z y x"], occupied: Bool[Tensor, "z1 y1 x1"],
) -> Bake:
    """Cut the dense vertex arrays into the bricks that hold a ``stored`` vertex; quantize each
    brick's colour channels to 8 bits over the range of its ``needed`` vertices (those of
    occupied cells; ``stored`` adds the vertices a normal's probes read)."""
    b = header.brick
    bx, by, bz = header.brick_grid
    nz, ny, nx = needed.shape
    pad = (0, bx * b - nx, 0, by * b - ny, 0, bz * b - nz)
    need = F.pad(stored.float(), pad).view(bz, b, by, b, bx, b).permute(0, 2, 4, 1, 3, 5).reshape(bz, by, bx, -1)
    keep = need.amax(-1) > 0  # [bz, by, bx]
    kept = keep.nonzero()  # [n, 3] as z, y, x
    c = coefficients.shape[-1]

    def blocks(values: Tensor, fill: float) -> Tensor:
        padded = F.pad(values.movedim(-1, 0), pad, value=fill)  # [ch, Z, Y, X]
        cut = padded.view(-1, bz, b, by, b, bx, b).permute(1, 3, 5, 2, 4, 6, 0)  # [bz, by, bx, b, b, b, ch]
        return cut[kept[:, 0], kept[:, 1], kept[:, 2]]

    raw_b = blocks(raw[..., None], DENSITY_FILL)[..., 0]  # [n, b, b, b]
    coef_b = blocks(coefficients, 0.0)  # [n, b, b, b, c]
    need_b = blocks(needed[..., None].float(), 0.0)[..., 0] > 0
    big = torch.finfo(torch.float32).max
    masked = need_b[..., None]
    low = torch.where(masked, coef_b, big).amin(dim=(1, 2, 3))  # [n, c]
    high = torch.where(masked, coef_b, -big).amax(dim=(1, 2, 3))
    step = ((high - low) / 255.0).clamp_min(0.0)
    codes = ((coef_b - low[:, None, None, None]) / step.clamp_min(1e-30)[:, None, None, None]).round()
    codes = torch.where(masked, codes.clamp(0, 255), 0.0).to(torch.uint8)
    occ_bits = np.packbits(occupied.numpy().reshape(-1), bitorder="little")
    bake = Bake(header, bricks=kept.flip(-1).numpy().astype(np.int16), raw=raw_b.numpy().astype(np.float16),
                codes=codes.numpy().reshape(-1, b, b, b, c), low=low.numpy().astype(np.float32),
                scale=step.numpy().astype(np.float32), occupancy=occ_bits)
    bake.check()
    return bake


def content_hash(data: bytes) -> str:
    """The first 16 hex digits of a SHA-256: a checkpoint's identity in a bake's source."""
    return hashlib.sha256(data).hexdigest()[:16]
