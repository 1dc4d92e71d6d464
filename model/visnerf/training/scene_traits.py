"""What the recipe reads from a dataset's images and cameras (``training.recipe``): the size of a
pixel at the content, whether every image frames its content whole, how much of the foreground
is faint (translucent content) or not (opaque surfaces), and how many views see each setting."""

from dataclasses import dataclass

import torch

from visnerf.config.recipe import RECIPE
from visnerf.data.carving import foreground_masks
from visnerf.data.scene import SceneData, estimate_bbox


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
    """Fraction of the foreground pixels that are faint (``RECIPE.faint_contrast``)."""
    n_params: int
    views_per_setting: float
    """Training images of a parameter setting (the median over settings; every image for K = 0)."""

    @property
    def opaque(self) -> bool:
        return self.faint_fraction < RECIPE.surface_max_faint


def pixel_footprint(scene: SceneData, centre: torch.Tensor) -> float:
    """World size of a pixel at ``centre``: the median over views of the camera's distance to it over
    the focal length (pixels); an orthographic camera's pixels have one size at every depth."""
    dist = torch.linalg.norm(scene.c2w[:, :3, 3].float() - centre.float()[None], dim=-1)  # [n]
    k = scene.intrinsics
    return 1.0 / max(k.fx, k.fy) if k.orthographic else float(dist.median()) / max(k.fx, k.fy)


def frames_cut_by_border(scene: SceneData, tolerance: int, chunk: int = 64) -> int:
    """Training images with a foreground pixel (farther than ``tolerance`` from the background)
    within ``RECIPE.border_pixels`` of the image's edge."""
    count, b = 0, RECIPE.border_pixels
    for start in range(0, scene.n_frames, chunk):
        fg = foreground_masks(scene.images[start : start + chunk], scene.background, tolerance, 0)  # [c, h, w]
        edge = fg[:, :b, :].flatten(1).any(1) | fg[:, -b:, :].flatten(1).any(1)
        edge |= fg[:, :, :b].flatten(1).any(1) | fg[:, :, -b:].flatten(1).any(1)
        count += int(edge.sum())
    return count


def faint_fraction(scene: SceneData, tolerance: int, max_frames: int = 64) -> float:
    """Fraction of the foreground pixels (of up to ``max_frames`` evenly chosen training images)
    whose difference from the background is below ``RECIPE.faint_contrast`` of the foreground's 99th
    percentile difference: the soft fringe of translucent content; 0 for opaque surfaces."""
    pick = torch.linspace(0, scene.n_frames - 1, min(max_frames, scene.n_frames)).round().long().unique()
    background = (torch.tensor(scene.background) * 255.0).round().to(torch.int16)
    diff = (scene.images[pick].to(torch.int16) - background).abs().amax(dim=-1)  # [n, h, w]
    fg = diff[diff > tolerance].float()  # [m]
    if fg.numel() == 0:
        return 1.0  # nothing but background: no evidence of a surface
    top = torch.quantile(fg[:: max(1, fg.numel() // 100_000)], 0.99)
    return float((fg < RECIPE.faint_contrast * top).float().mean())


def views_per_setting(scene: SceneData) -> float:
    """The median number of training images at one parameter setting."""
    if scene.n_params == 0:
        return float(scene.n_frames)
    _, counts = torch.unique(scene.params, dim=0, return_counts=True)
    return float(counts.float().median())


def scene_traits(scene: SceneData, tolerance: int) -> SceneTraits:
    box = estimate_bbox(scene)
    border = frames_cut_by_border(scene, tolerance)
    return SceneTraits(pixel_footprint(scene, box.mean(dim=0)), border == 0, border,
                       faint_fraction(scene, tolerance), scene.n_params, views_per_setting(scene))
