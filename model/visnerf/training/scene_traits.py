"""What the recipe reads from a dataset's images and cameras (``training.recipe``): the size of a
pixel at the content, whether every image frames its content whole, and how much of the foreground
is faint (translucent content) or not (opaque surfaces)."""

from dataclasses import dataclass

import torch

from visnerf.data.carving import foreground_masks
from visnerf.data.scene import SceneData, estimate_bbox

FAINT_CONTRAST = 0.25
"""A foreground pixel is faint when its difference from the background is below this fraction of
the 99th percentile of the foreground's differences."""
SURFACE_MAX_FAINT = 0.01
"""Most faint foreground pixels (a fraction) for a scene to count as opaque surfaces: isosurface
renderings have none, volume renderings several per cent (docs/decisions.md, "Recipe: grid and
carving")."""
BORDER_PIXELS = 1
"""Width of the image border in which a foreground pixel means content cut by the frame."""


@dataclass(frozen=True)
class SceneTraits:
    """What the recipe reads from a dataset."""

    pixel_footprint: float
    """World size of one pixel at the content's centre (median over the training views)."""
    framed: bool
    """Every training image shows its content clear of the image border."""
    border_frames: int
    """Training images with foreground on their border."""
    faint_fraction: float
    """Fraction of the foreground pixels that are faint (``FAINT_CONTRAST``)."""
    n_params: int

    @property
    def opaque(self) -> bool:
        return self.faint_fraction < SURFACE_MAX_FAINT


def pixel_footprint(scene: SceneData, centre: torch.Tensor) -> float:
    """World size of a pixel at ``centre``: the median over views of the camera's distance to it over
    the focal length (pixels); an orthographic camera's pixels have one size at every depth."""
    dist = torch.linalg.norm(scene.c2w[:, :3, 3].float() - centre.float()[None], dim=-1)  # [n]
    k = scene.intrinsics
    return 1.0 / max(k.fx, k.fy) if k.orthographic else float(dist.median()) / max(k.fx, k.fy)


def frames_cut_by_border(scene: SceneData, tolerance: int, chunk: int = 64) -> int:
    """Training images with a foreground pixel (farther than ``tolerance`` from the background)
    within ``BORDER_PIXELS`` of the image's edge."""
    count, b = 0, BORDER_PIXELS
    for start in range(0, scene.n_frames, chunk):
        fg = foreground_masks(scene.images[start : start + chunk], scene.background, tolerance, 0)  # [c, h, w]
        edge = fg[:, :b, :].flatten(1).any(1) | fg[:, -b:, :].flatten(1).any(1)
        edge |= fg[:, :, :b].flatten(1).any(1) | fg[:, :, -b:].flatten(1).any(1)
        count += int(edge.sum())
    return count


def faint_fraction(scene: SceneData, tolerance: int, max_frames: int = 64) -> float:
    """Fraction of the foreground pixels (of up to ``max_frames`` evenly chosen training images)
    whose difference from the background is below ``FAINT_CONTRAST`` of the foreground's 99th
    percentile difference: the soft fringe of translucent content; 0 for opaque surfaces."""
    pick = torch.linspace(0, scene.n_frames - 1, min(max_frames, scene.n_frames)).round().long().unique()
    background = (torch.tensor(scene.background) * 255.0).round().to(torch.int16)
    diff = (scene.images[pick].to(torch.int16) - background).abs().amax(dim=-1)  # [n, h, w]
    fg = diff[diff > tolerance].float()  # [m]
    if fg.numel() == 0:
        return 1.0  # nothing but background: no evidence of a surface
    top = torch.quantile(fg[:: max(1, fg.numel() // 100_000)], 0.99)
    return float((fg < FAINT_CONTRAST * top).float().mean())


def scene_traits(scene: SceneData, tolerance: int) -> SceneTraits:
    box = estimate_bbox(scene)
    border = frames_cut_by_border(scene, tolerance)
    return SceneTraits(pixel_footprint(scene, box.mean(dim=0)), border == 0, border,
                       faint_fraction(scene, tolerance), scene.n_params)
