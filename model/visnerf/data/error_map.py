"""Which training pixels to draw: a running estimate of each pixel tile's squared error.

Uniformly drawn pixels spend most of a batch where the model is already right: on Nyx, 63 to 69 %
of a training frame is background, and in the 60-minute model the worst 20 % of pixels hold 96 %
of the squared error (bench/results/nyx_error_concentration.md). Drawing a pixel with probability ``p`` and weighting its error by ``1 / p``
keeps the gradient an unbiased estimate of the uniform mean's and, with ``p`` following the error's
root (the optimal density for a gradient proportional to the residual), lowers its variance.

The error of each ``tile x tile`` block of each frame is estimated from the training rays that land
in it (an exponential average, the first visit replacing the optimistic start of 1, so that every
tile is measured before it can be neglected). A fraction ``uniform`` of the probability stays
uniform over the pixels: no pixel's weight exceeds ``1 / uniform``, and a tile whose estimate went
stale low is still revisited.
"""

from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from torch import Tensor


@dataclass(frozen=True)
class ErrorMapConfig:
    tile: int = 4
    """Pixels per side of a tile (the finer, the closer the draw follows the error, and the fewer
    rays each tile's estimate has)."""
    uniform: float = 0.2
    """Fraction of the probability spread uniformly over all pixels (bounds weights by its inverse)."""
    smoothing: float = 0.5
    """Weight of a new ray's error in its tile's running estimate (after the first visit)."""
    refresh_every: int = 32
    """Draws between rebuilds of the cumulative distribution from the estimates."""

    def __post_init__(self) -> None:
        if self.tile < 1:
            raise ValueError(f"tile must be at least 1 pixel, got {self.tile}")
        if not 0.0 < self.uniform <= 1.0:
            raise ValueError(f"uniform must be in (0, 1], got {self.uniform}")
        if not 0.0 < self.smoothing <= 1.0:
            raise ValueError(f"smoothing must be in (0, 1], got {self.smoothing}")
        if self.refresh_every < 1:
            raise ValueError(f"refresh_every must be at least 1, got {self.refresh_every}")


class PixelErrorMap:
    """Per-tile squared-error estimates of ``n_frames`` frames of ``height x width`` pixels, and
    draws of pixels in proportion to ``(1 - uniform) * sqrt(error) + uniform`` (each part
    normalised over the pixels)."""

    def __init__(self, n_frames: int, height: int, width: int, cfg: ErrorMapConfig) -> None:
        self.cfg = cfg
        self.n_frames, self.height, self.width = n_frames, height, width
        k = cfg.tile
        self.tiles_y, self.tiles_x = -(-height // k), -(-width // k)
        ty = torch.arange(self.tiles_y)
        tx = torch.arange(self.tiles_x)
        self.tile_h = (torch.clamp(height - ty * k, max=k))  # [tiles_y] rows in each tile row
        self.tile_w = (torch.clamp(width - tx * k, max=k))  # [tiles_x]
        self.pixels_per_tile = (self.tile_h[:, None] * self.tile_w[None, :]).reshape(-1).float()  # [ty*tx]
        self.pixels_all = self.pixels_per_tile.repeat(n_frames)  # [t]
        n_tiles = n_frames * self.tiles_y * self.tiles_x
        self.error: Float[Tensor, " t"] = torch.ones(n_tiles)
        """Running mean squared error (over RGB) of each tile's pixels; 1 (the most) until visited."""
        self.visited = torch.zeros(n_tiles, dtype=torch.bool)
        self.draws_since_refresh = cfg.refresh_every
        self.mass: Float[Tensor, " t"] = torch.empty(0)
        self.cdf: Float[Tensor, " t"] = torch.empty(0, dtype=torch.float64)

    def tile_masses(self) -> Float[Tensor, " t"]:
        """Probability of drawing a pixel in each tile (float32; sums to 1 up to rounding)."""
        root = self.error.clamp_min(0.0).sqrt() * self.pixels_all  # a tile's share: its pixels' root error
        total = float(root.sum(dtype=torch.float64))
        n_pixels = self.n_frames * self.height * self.width
        if not total > 0.0:  # every estimate is 0: nothing to prefer
            return self.pixels_all / n_pixels
        return root * ((1.0 - self.cfg.uniform) / total) + self.pixels_all * (self.cfg.uniform / n_pixels)

    def refresh(self) -> None:
        self.mass = self.tile_masses()
        self.cdf = torch.cumsum(self.mass, 0, dtype=torch.float64)  # float64: 1e6+ tiles of ~1e-7 each
        self.draws_since_refresh = 0

    def draw(
        self, n: int, generator: torch.Generator,
    ) -> tuple[Int[Tensor, " n"], Int[Tensor, " n"], Int[Tensor, " n"], Float[Tensor, " n"]]:
        """``n`` pixels (frame, x, y) and each one's importance weight ``1 / (pixels * p)``, where
        ``p`` is its probability (1 for every pixel of a uniform draw)."""
        if self.draws_since_refresh >= self.cfg.refresh_every:
            self.refresh()
        self.draws_since_refresh += 1
        u = torch.rand(n, generator=generator, dtype=torch.float64) * float(self.cdf[-1])
        tile = torch.searchsorted(self.cdf, u, right=True).clamp_max(self.cdf.numel() - 1)  # [n]
        per_frame = self.tiles_y * self.tiles_x
        frame, within = tile // per_frame, tile % per_frame
        ty, tx = within // self.tiles_x, within % self.tiles_x
        k = self.cfg.tile
        fy = torch.rand(n, generator=generator)
        fx = torch.rand(n, generator=generator)
        py = ty * k + (fy * self.tile_h[ty]).long().clamp_max(self.tile_h[ty] - 1)
        px = tx * k + (fx * self.tile_w[tx]).long().clamp_max(self.tile_w[tx] - 1)
        pixel_p = self.mass[tile].double() / (float(self.cdf[-1]) * self.pixels_per_tile[within].double())  # [n]
        weight = (1.0 / (pixel_p * (self.n_frames * self.height * self.width))).float()
        return frame, px, py, weight

    def tile_of(self, frame: Tensor, px: Tensor, py: Tensor) -> Tensor:
        k = self.cfg.tile
        return (frame * self.tiles_y + py // k) * self.tiles_x + px // k

    def record(self, frame: Tensor, px: Tensor, py: Tensor, sq_error: Float[Tensor, " n"]) -> None:
        """Fold the measured squared errors (mean over RGB) of pixels into their tiles' estimates.
        Non-finite errors are ignored."""
        tile = self.tile_of(frame.cpu(), px.cpu(), py.cpu())
        err = sq_error.detach().float().cpu()
        ok = torch.isfinite(err)
        tile, err = tile[ok], err[ok].clamp(0.0, 1.0)
        old = self.error[tile]
        beta = self.cfg.smoothing
        self.error[tile] = torch.where(self.visited[tile], (1.0 - beta) * old + beta * err, err)
        self.visited[tile] = True
