"""Random ray batches made on the fly from uint8 images (no per-pixel ray storage)."""

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from jaxtyping import Float, Int, UInt8
from torch import Tensor

from visnerf.data.cameras import rays_from_pixels
from visnerf.data.carving import foreground_masks
from visnerf.data.scene import SceneData
from visnerf.rendering.aabb import intersect_aabb


@dataclass
class RayBatch:
    rays_o: Float[Tensor, "n 3"]
    rays_d: Float[Tensor, "n 3"]
    rgb: Float[Tensor, "n 3"]
    params: Float[Tensor, "n k"]
    """Normalised parameter values."""
    frame: Int[Tensor, " n"]
    px: Int[Tensor, " n"]
    py: Int[Tensor, " n"]


def silhouette_pixels(
    images: UInt8[Tensor, "n h w 3"], background: tuple[float, float, float], tolerance: int, chunk: int = 64
) -> Int[Tensor, " m"]:
    """Flat indices (``frame * h * w + y * w + x``) of the pixels within one pixel (8-neighbourhood)
    of a boundary between background and content: content pixels with a background neighbour and
    background pixels with a content neighbour. Pixels farther than ``tolerance`` (0-255) from the
    background in any channel are content; the image border is no boundary."""
    n, h, w, _ = images.shape
    out = []
    for start in range(0, n, chunk):
        fg = foreground_masks(images[start : start + chunk], background, tolerance, 0).float()[:, None]  # [c, 1, h, w]
        any_fg = F.max_pool2d(fg, 3, stride=1, padding=1)  # a content pixel within the 3x3 window
        any_bg = -F.max_pool2d(-fg, 3, stride=1, padding=1) < 1.0  # a background pixel within it
        band = (any_fg[:, 0] > 0) & any_bg[:, 0]  # [c, h, w]
        # padding counts as neither: max_pool2d pads with -inf, so the border adds no boundary
        out.append(band.reshape(-1).nonzero()[:, 0] + start * h * w)
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.long)


REDRAW_MARGIN = 1.25
"""Candidates a redraw round draws, over the count its share of hits would need: a round falls
short of the missing rays only rarely (the next round then draws for the rest)."""
MIN_HIT_SHARE = 0.05
"""The least share of hits a redraw round assumes, so that a box hardly any ray hits does not
draw twenty times the batch."""


class RayBatchSampler:
    """Uniformly random pixels of random frames; rays that miss ``aabb`` are redrawn.

    Missing the content box means the pixel can only show the background, which the box already
    guarantees, so such rays are filtered (up to ``max_redraws`` rounds). A round draws enough
    candidates for the rays still missing at the share of hits seen so far (``REDRAW_MARGIN``) and
    gives each missing ray the next hit in draw order: rejection sampling, so the kept rays are
    uniform over the pixels whose rays hit, and a round's fixed cost is paid once or twice a batch
    rather than once per share of misses. With a silhouette band
    (``set_silhouette_band``), a fixed share of each batch is drawn uniformly from the band's pixels
    instead: an emphasis, not an unbiased estimate, on the pixels where an opaque surface's error lies.
    """

    def __init__(self, scene: SceneData, device: torch.device, generator: torch.Generator) -> None:
        self.scene = scene
        self.device = device
        self.generator = generator
        self.params_norm = scene.normalized_params()
        self.aabb: Tensor | None = None
        self.band: Int[Tensor, " m"] | None = None
        self.band_fraction = 0.0

    def set_silhouette_band(self, band: Int[Tensor, " m"] | None, fraction: float) -> None:
        """Draw ``fraction`` of each batch from the flat pixel indices ``band`` (``silhouette_pixels``);
        an empty band or a fraction of 0 draws every ray from every pixel."""
        if not 0.0 <= fraction < 1.0:
            raise ValueError(f"the silhouette share must be in [0, 1), got {fraction}")
        empty = band is None or band.numel() == 0 or fraction == 0.0
        self.band = None if empty else band.to(torch.long).cpu()
        self.band_fraction = 0.0 if empty else fraction

    def set_aabb(self, aabb: Tensor | None) -> None:
        self.aabb = None if aabb is None else aabb.detach().cpu()

    def _draw(self, n: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        s = self.scene
        frame = torch.randint(0, s.n_frames, (n,), generator=self.generator)
        px = torch.randint(0, s.intrinsics.width, (n,), generator=self.generator)
        py = torch.randint(0, s.intrinsics.height, (n,), generator=self.generator)
        rays_o, rays_d = self._pixel_rays(frame, px, py)
        return frame, px, py, rays_o, rays_d, self._hits(rays_o, rays_d)

    def _pixel_rays(self, frame: Tensor, px: Tensor, py: Tensor) -> tuple[Tensor, Tensor]:
        """Rays through the centres of pixels (px, py) of these frames."""
        s = self.scene
        return rays_from_pixels(s.c2w.index_select(0, frame), s.intrinsics, px.float() + 0.5, py.float() + 0.5)

    def _hits(self, rays_o: Tensor, rays_d: Tensor) -> Tensor:
        if self.aabb is None:
            return torch.ones(rays_o.shape[0], dtype=torch.bool)
        return intersect_aabb(rays_o, rays_d, self.aabb)[2]

    def _pixels(self, frame: Tensor, px: Tensor, py: Tensor) -> Tensor:
        """The images' colours at these pixels, ``[n, 3]`` uint8 (``index_select`` on the flat
        pixels: advanced indexing costs several times as much a call on the CPU)."""
        images = self.scene.images
        if not images.is_contiguous():
            return images[frame, py, px]
        _, h, w, c = images.shape
        return images.view(-1, c).index_select(0, (frame * h + py) * w + px)

    def _draw_band(self, n: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        assert self.band is not None
        s = self.scene
        h, w = s.intrinsics.height, s.intrinsics.width
        flat = self.band.index_select(0, torch.randint(0, self.band.numel(), (n,), generator=self.generator))
        frame, pixel = flat // (h * w), flat % (h * w)
        py, px = pixel // w, pixel % w
        return frame, px, py, *self._pixel_rays(frame, px, py)

    def sample(self, n: int, max_redraws: int = 4) -> RayBatch:
        n_band = min(int(round(self.band_fraction * n)), n - 1) if self.band is not None else 0
        frame, px, py, rays_o, rays_d, hit = self._draw(n - n_band)
        drawn, hits = hit.numel(), int(hit.sum())
        for _ in range(max_redraws):
            miss = (~hit).nonzero()[:, 0]
            if miss.numel() == 0:
                break
            share = max(hits / max(drawn, 1), MIN_HIT_SHARE)
            f2, x2, y2, o2, d2, h2 = self._draw(math.ceil(miss.numel() / share * REDRAW_MARGIN))
            drawn, hits = drawn + h2.numel(), hits + int(h2.sum())
            take = h2.nonzero()[: miss.numel(), 0]  # the first hits, in draw order
            slots = miss[: take.numel()]
            for into, source in ((frame, f2), (px, x2), (py, y2), (rays_o, o2), (rays_d, d2), (hit, h2)):
                into.index_copy_(0, slots, source.index_select(0, take))
        if n_band > 0:  # kept even where a ray misses the box: background beside content
            fb, xb, yb, ob, db = self._draw_band(n_band)
            frame, px, py = torch.cat([frame, fb]), torch.cat([px, xb]), torch.cat([py, yb])
            rays_o, rays_d = torch.cat([rays_o, ob]), torch.cat([rays_d, db])
        rgb = self._pixels(frame, px, py).float() / 255.0
        return RayBatch(
            rays_o.to(self.device),
            rays_d.to(self.device),
            rgb.to(self.device),
            self.params_norm.index_select(0, frame).to(self.device),
            frame, px, py,
        )


def micro_batches(per_ray: Int[Tensor, " n"], max_rays: int, max_samples: int) -> list[slice]:
    """Consecutive slices of a batch whose rays evaluate ``per_ray`` samples each
    (``RaySamples.per_ray``), with at most ``max_rays`` rays and, where a single ray does not
    exceed it alone, at most ``max_samples`` samples per slice.

    Activation memory grows with the samples evaluated and back-propagated, so a sample budget
    keeps it flat as the grid (and with it the samples per ray) grows, and in a fresh field's fog,
    where every sample in the box is evaluated. Once content is carved or learned, most samples in
    the box are skipped and the same budget holds many more rays: each micro-batch costs its
    backward pass's fixed work (a sort of its taps per table, the decoders' weight gradients), so
    fewer, fuller micro-batches are faster.
    """
    if 0 < per_ray.shape[0] <= max_rays and int(per_ray.sum()) <= max_samples:
        return [slice(0, per_ray.shape[0])]  # the common case, without a loop over the rays in Python
    counts = per_ray.tolist()
    slices, start, total = [], 0, 0
    for i, c in enumerate(counts):
        if i > start and (i - start >= max_rays or total + c > max_samples):
            slices.append(slice(start, i))
            start, total = i, 0
        total += c
    if start < len(counts):
        slices.append(slice(start, len(counts)))
    return slices
