"""Random ray batches made on the fly from uint8 images (no per-pixel ray storage)."""

from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from torch import Tensor

from visnerf.data.cameras import rays_from_pixels
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


class RayBatchSampler:
    """Uniformly random pixels of random frames; rays that miss ``aabb`` are redrawn.

    Missing the content box means the pixel can only show the background, which the box already
    guarantees, so such rays are filtered (up to ``max_redraws`` rounds).
    """

    def __init__(self, scene: SceneData, device: torch.device, generator: torch.Generator) -> None:
        self.scene = scene
        self.device = device
        self.generator = generator
        self.params_norm = scene.normalized_params()
        self.aabb: Tensor | None = None

    def set_aabb(self, aabb: Tensor | None) -> None:
        self.aabb = None if aabb is None else aabb.detach().cpu()

    def _draw(self, n: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        s = self.scene
        frame = torch.randint(0, s.n_frames, (n,), generator=self.generator)
        px = torch.randint(0, s.intrinsics.width, (n,), generator=self.generator)
        py = torch.randint(0, s.intrinsics.height, (n,), generator=self.generator)
        rays_o, rays_d = rays_from_pixels(s.c2w[frame], s.intrinsics, px.float() + 0.5, py.float() + 0.5)
        return frame, px, py, rays_o, rays_d, self._hits(rays_o, rays_d)

    def _hits(self, rays_o: Tensor, rays_d: Tensor) -> Tensor:
        if self.aabb is None:
            return torch.ones(rays_o.shape[0], dtype=torch.bool)
        return intersect_aabb(rays_o, rays_d, self.aabb)[2]

    def sample(self, n: int, max_redraws: int = 4) -> RayBatch:
        frame, px, py, rays_o, rays_d, hit = self._draw(n)
        for _ in range(max_redraws):
            miss = (~hit).nonzero()[:, 0]
            if miss.numel() == 0:
                break
            f2, x2, y2, o2, d2, h2 = self._draw(miss.numel())
            frame[miss], px[miss], py[miss] = f2, x2, y2
            rays_o[miss], rays_d[miss], hit[miss] = o2, d2, h2
        rgb = self.scene.images[frame, py, px].float() / 255.0  # [n, 3]
        return RayBatch(
            rays_o.to(self.device),
            rays_d.to(self.device),
            rgb.to(self.device),
            self.params_norm[frame].to(self.device),
            frame, px, py,
        )
