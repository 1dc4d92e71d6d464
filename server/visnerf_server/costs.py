"""What a frame may cost: the size limits every render request is checked against (HTTP and
stream alike, in ``frames.prepare_frame``) and the frame's price for the per-client rate limit.

A frame's render time grows with its pixel count (bench/results/render_speed.md), so the limits are
pixel budgets per quality: a width or height over ``max_side`` or a width x height over the
quality's budget is refused (422) naming the limit and the size asked for.
"""

import math
from dataclasses import dataclass

from visnerf_server.settings import MIN_FRAME_PIXELS, Settings


class FrameTooLarge(ValueError):
    """A requested frame is over this server's size limits (the message names limit and size)."""


@dataclass(frozen=True)
class FrameLimits:
    max_side: int
    """Largest width or height."""
    max_preview_pixels: int
    max_full_pixels: int
    preview_pixel_cost: float = 1.0
    """Rate-limit price of a preview pixel, a full-quality pixel costing 1."""

    @classmethod
    def from_settings(cls, settings: Settings) -> "FrameLimits":
        return cls(
            settings.max_image_size,
            settings.max_preview_pixels,
            settings.max_full_pixels,
            settings.preview_pixel_cost,
        )

    def max_pixels(self, quality: str) -> int:
        return self.max_preview_pixels if quality == "preview" else self.max_full_pixels

    def check(self, width: int, height: int, quality: str) -> None:
        """Raise FrameTooLarge when ``width`` x ``height`` is over a limit for ``quality``."""
        for name, value in (("width", width), ("height", height)):
            if value > self.max_side:
                raise FrameTooLarge(f"{name} {value} exceeds this server's limit of {self.max_side} pixels")
        budget = self.max_pixels(quality)
        if width * height > budget:
            raise FrameTooLarge(
                f"a {quality} frame of {width}x{height} = {width * height} pixels exceeds this server's "
                f"limit of {budget} pixels for {quality} frames (max_{quality}_pixels)"
            )

    def default_size(self, width: int, height: int, quality: str) -> tuple[int, int]:
        """A frame size for a request that gives none: ``width`` x ``height`` (the scene's trained
        size) scaled down, aspect kept, until it fits every limit for ``quality``."""
        scale = min(1.0, self.max_side / max(width, height), math.sqrt(self.max_pixels(quality) / (width * height)))
        side = math.isqrt(MIN_FRAME_PIXELS)
        return max(side, math.floor(width * scale)), max(side, math.floor(height * scale))

    def cost(self, width: int, height: int, quality: str) -> float:
        """The frame's price in full-quality pixels."""
        return width * height * (self.preview_pixel_cost if quality == "preview" else 1.0)
