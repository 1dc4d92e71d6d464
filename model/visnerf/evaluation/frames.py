"""Render one evaluation frame with given settings and time it.

The frame is rendered at ``settings.resolution_scale`` of the camera's size, upsampled bilinearly to
full size (as the server's preview does) and quantised to 8 bits, since 8-bit images are what a
client receives and what the ground truth is. The time covers all of that, on ``field``'s device.
"""

import time
from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from visnerf.checkpoint import ParamAxis
from visnerf.data.cameras import Intrinsics
from visnerf.rendering.render_settings import RenderSettings
from visnerf.rendering.renderer import render_image_scaled
from visnerf.representation.field import VisNerfField


@dataclass(frozen=True)
class RenderedFrame:
    """A synthesized frame and the milliseconds it took."""

    rgb: Float[np.ndarray, "h w 3"]
    """8-bit quantised colours as float32 in [0, 1]."""
    ms: float


def normalize_params(axes: tuple[ParamAxis, ...], raw: Float[np.ndarray, " k"]) -> Float[Tensor, " k"]:
    """Raw parameter values -> the field's [-1, 1] coordinates, axis by axis."""
    return torch.tensor([axis.normalize(float(v)) for axis, v in zip(axes, raw, strict=True)], dtype=torch.float32)


def render_frame(
    field: VisNerfField,
    c2w: Float[Tensor, "4 4"],
    intrinsics: Intrinsics,
    params: Float[Tensor, " k"],
    settings: RenderSettings,
) -> RenderedFrame:
    """Render and time one frame (``params`` normalised, see ``normalize_params``)."""
    device = field.device
    c2w_d, params_d = c2w.to(device=device, dtype=torch.float32), params.to(device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    with torch.inference_mode():
        rgb = render_image_scaled(field, c2w_d, intrinsics, params_d, settings)  # [h, w, 3]
        quantised = (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()  # waits for the device
    ms = 1000.0 * (time.perf_counter() - t0)
    return RenderedFrame(rgb=quantised.astype(np.float32) / 255.0, ms=float(ms))
