"""Frames larger than the model's detail: march a lattice of pixels, then only the cells that differ.

A frame shown at a screen's size is often several times the size of the training images, and the
field holds no detail finer than a voxel except where its decoders turn sharply (an isosurface's
edge, a silhouette). ``refine_frame`` marches every ``spacing``-th pixel in both directions
(always including the last row and column), then halves the spacing until it is one: a cell of the
current lattice whose four corner pixels differ by more than ``spread`` in some channel has its
new lattice pixels marched; every other new pixel is the bilinear blend of its cell's corners
(adaptive subsampling, as ray tracers have done since Whitted, 1980). ``refinement_spacing``
chooses the spacing from the projected size of a voxel, so that a cell never spans more than one
voxel of the content on screen: a feature the corners miss is thinner than a voxel.
"""

import math
from collections.abc import Callable

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from visnerf.data.cameras import Intrinsics, project_points

PixelRenderer = Callable[[Int[Tensor, " n"], Int[Tensor, " n"]], Float[Tensor, "n 3"]]
"""Colours of the pixels at columns ``u`` and rows ``v`` (whole pixel indices)."""


def lattice(size: int, spacing: int, device: torch.device) -> Int[Tensor, " m"]:
    """Pixel indices ``0, spacing, 2 spacing, ...`` below ``size``, and ``size - 1`` (the image's
    last row or column is always on the lattice, so every pixel lies within a cell)."""
    points = torch.arange(0, size, spacing, device=device)
    if int(points[-1]) != size - 1:
        points = torch.cat([points, torch.tensor([size - 1], device=device)])
    return points


def refinement_spacing(box: Float[Tensor, "2 3"], voxel: float, c2w: Float[Tensor, "4 4"], intrinsics: Intrinsics,
                       largest: int) -> int:
    """The largest power of two, at most ``largest``, that is at most the size in pixels of a voxel
    (edge ``voxel``) at the far corner of ``box`` (the smallest it appears anywhere in the box;
    1 where the box is not wholly in front of a perspective camera)."""
    corners = torch.stack(torch.meshgrid(*(box[:, i] for i in range(3)), indexing="ij"), dim=-1).reshape(8, 3)
    _, depth = project_points(c2w, intrinsics, corners.to(c2w.dtype))
    far = float(depth.max())
    if not intrinsics.orthographic and not (float(depth.min()) > 0.0):
        return 1
    pixel = intrinsics.pixel_size(far)
    pixels = voxel / pixel if math.isfinite(pixel) and pixel > 0.0 else 0.0
    if not (math.isfinite(pixels) and pixels >= 2.0):  # an extreme lens: every pixel marched
        return 1
    return int(min(largest, 2 ** math.floor(math.log2(pixels))))


def _cell_spread(values: Float[Tensor, "r c 3"]) -> Float[Tensor, "r-1 c-1"]:
    """Per cell of a lattice of colours: the largest channel's range over its four corners."""
    corners = torch.stack([values[:-1, :-1], values[:-1, 1:], values[1:, :-1], values[1:, 1:]])  # [4, r-1, c-1, 3]
    return (corners.amax(dim=0) - corners.amin(dim=0)).amax(dim=-1)


def _cells_of(coarse: Int[Tensor, " r"], fine: Int[Tensor, " f"],
              dtype: torch.dtype) -> tuple[Int[Tensor, " f"], Float[Tensor, " f"]]:
    """For each fine lattice index: the cell of the coarse lattice it lies in (the last cell for
    the last index) and its fraction of the way across that cell."""
    cell = (torch.searchsorted(coarse, fine, right=True) - 1).clamp(0, coarse.numel() - 2)
    lo, hi = coarse[cell], coarse[cell + 1]
    return cell, (fine - lo).to(dtype) / (hi - lo).to(dtype)


def refine_frame(render: PixelRenderer, height: int, width: int, spacing: int, spread: float,
                 device: torch.device, dtype: torch.dtype = torch.float32) -> Float[Tensor, "h w 3"]:
    """The frame from ``render`` marching a lattice ``spacing`` pixels apart and, level by level,
    only the pixels of cells whose corners differ by more than ``spread`` (module docstring). With
    ``spacing`` 1, or a frame too small for one cell of it, every pixel is marched."""
    while spacing > 1 and min(height, width) < 2 * spacing:
        spacing //= 2
    if spacing <= 1:
        vv, uu = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij")
        return render(uu.reshape(-1), vv.reshape(-1)).reshape(height, width, 3)
    image = torch.empty(height, width, 3, dtype=dtype, device=device)
    rows, cols = lattice(height, spacing, device), lattice(width, spacing, device)
    vv, uu = torch.meshgrid(rows, cols, indexing="ij")
    image[vv, uu] = render(uu.reshape(-1), vv.reshape(-1)).reshape(rows.numel(), cols.numel(), 3)
    while spacing > 1:
        spacing //= 2
        fine_rows, fine_cols = lattice(height, spacing, device), lattice(width, spacing, device)
        corners = image[rows][:, cols]  # [r, c, 3]
        flagged = _cell_spread(corners) > spread  # [r-1, c-1]
        cell_r, frac_r = _cells_of(rows, fine_rows, dtype)
        cell_c, frac_c = _cells_of(cols, fine_cols, dtype)
        known = _on_lattice(rows, fine_rows)[:, None] & _on_lattice(cols, fine_cols)[None, :]  # [fr, fc]
        march: Bool[Tensor, "fr fc"] = flagged[cell_r][:, cell_c] & ~known
        blend = ~march & ~known
        if bool(blend.any()):
            i, j = blend.nonzero(as_tuple=True)
            a, b = cell_r[i], cell_c[j]
            ty, tx = frac_r[i, None], frac_c[j, None]
            top = corners[a, b] * (1 - tx) + corners[a, b + 1] * tx
            bottom = corners[a + 1, b] * (1 - tx) + corners[a + 1, b + 1] * tx
            image[fine_rows[i], fine_cols[j]] = top * (1 - ty) + bottom * ty
        if bool(march.any()):
            i, j = march.nonzero(as_tuple=True)
            image[fine_rows[i], fine_cols[j]] = render(fine_cols[j], fine_rows[i])
        rows, cols = fine_rows, fine_cols
    return image


def _on_lattice(coarse: Int[Tensor, " r"], fine: Int[Tensor, " f"]) -> Bool[Tensor, " f"]:
    """Which fine lattice indices the coarse lattice holds."""
    return torch.isin(fine, coarse)
