"""The settings of one render call: spacing, thresholds, chunks and segments, derived from a
checkpoint's ``RenderConfig`` and a quality (``full``, ``preview`` or ``exhaustive``)."""

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Literal

import torch

from visnerf.config import FramesConfig, RenderConfig
from visnerf.runtime import batch_factor

if TYPE_CHECKING:
    from visnerf.checkpoint import CheckpointMeta


Quality = Literal["preview", "full"]
"""The qualities a frame is asked for (the server, ``visnerf render``, movies)."""
RenderQuality = Literal["preview", "full", "exhaustive"]
"""The qualities of a render call: those, and the exhaustive reference (evaluation, calibration)."""

DEFAULT_FRAMES = FramesConfig()
"""Chunks and segments of a render call that is given none."""
EXHAUSTIVE_STEP_RATIO = 0.5
"""Sample spacing of the exhaustive reference, in voxels, at most: the paper's training spacing."""


EXHAUSTIVE_CHUNK_RAYS = 1024
"""Rays per chunk of an exhaustive frame, at most: every sample of every ray is shaded, so a chunk's
buffers grow with its rays times its segment; fewer rays bound the memory and cost no time (the
end of training renders such frames to choose the spacing; docs/decisions.md#render.exhaustive)."""


def rays_per_chunk(settings: "RenderSettings", device: torch.device) -> int:
    """Rays a chunk of a frame holds on ``device``: ``settings.chunk_rays`` on the CPU, where
    chunks go to one thread per core; more on a GPU (``runtime.batch_factor``)."""
    return settings.chunk_rays * batch_factor(device)


def exhaustive_step_ratio(cfg: RenderConfig) -> float:
    """The exhaustive reference's spacing: the finer of the training spacing and half a voxel, so
    that a model trained with coarser samples is still judged against finely sampled frames."""
    return min(cfg.step_ratio, EXHAUSTIVE_STEP_RATIO)


@dataclass(frozen=True)
class RenderSettings:
    """Settings of one render call (derived from the checkpoint's RenderConfig and a quality)."""

    step_ratio: float = 0.5
    max_samples: int = 1024
    weight_threshold_per_voxel: float = 1e-4
    """Samples whose compositing weight is at most this times ``step_ratio`` skip colour decoding
    (``RenderConfig.full_weight_threshold_per_voxel``); 0 decodes every sample."""
    early_stop_eps: float = 1e-4
    chunk_rays: int = FramesConfig.chunk_rays
    """Rays per chunk of a frame (inference; ``FramesConfig``, the machine's, not the model's)."""
    segment_samples: int = FramesConfig.segment_samples
    first_segment_samples: int = FramesConfig.first_segment_samples
    refine_spacing: int = 1
    """Largest lattice spacing of a full-scale frame (``FramesConfig.refine_spacing``; 1: every
    pixel marched, as the exhaustive reference always is)."""
    refine_spread: float = FramesConfig.refine_spread
    resolution_scale: float = 1.0
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    use_occupancy: bool = True
    early_termination: bool = True
    bf16: bool = False
    """Decoder matrix products in bfloat16 where the device has bf16 matrix units (inference)."""

    @classmethod
    def from_config(
        cls, cfg: RenderConfig, background: tuple[float, float, float], quality: RenderQuality = "full",
        frames: FramesConfig = DEFAULT_FRAMES,
    ) -> "RenderSettings":
        """``full``: as the server renders; ``preview``: smaller and coarser; ``exhaustive``: the
        plain reference (``exhaustive_step_ratio``, every sample in the model's occupancy grid,
        float32). ``frames``: this machine's chunks and segments.

        The reference marches the grid because the grid is part of the model: training fits only
        the cells it keeps, and outside them the density has had no photometric loss since the grid
        was last narrowed, and marched everywhere the reference scores far under the frames it
        judges (docs/decisions.md#render.exhaustive; ``evaluation.spacing``)."""
        if quality not in ("full", "preview", "exhaustive"):
            raise ValueError(f"quality must be 'full', 'preview' or 'exhaustive', got {quality!r}")
        settings = cls(
            step_ratio=cfg.full_step_ratio,
            max_samples=cfg.max_samples,
            weight_threshold_per_voxel=cfg.full_weight_threshold_per_voxel,
            early_stop_eps=cfg.early_stop_eps,
            background=background,
            bf16=cfg.bf16,
            chunk_rays=frames.chunk_rays,
            segment_samples=frames.segment_samples,
            first_segment_samples=frames.first_segment_samples,
            refine_spacing=frames.refine_spacing,
            refine_spread=frames.refine_spread,
        )
        if quality == "exhaustive":
            settings = replace(settings, step_ratio=exhaustive_step_ratio(cfg), early_termination=False,
                               weight_threshold_per_voxel=0.0, bf16=False, refine_spacing=1,
                               chunk_rays=min(frames.chunk_rays, EXHAUSTIVE_CHUNK_RAYS))
        elif quality == "preview":
            settings = replace(
                settings,
                step_ratio=exhaustive_step_ratio(cfg) * cfg.preview_step_factor,
                resolution_scale=cfg.preview_scale,
            )
        return settings

    @classmethod
    def from_meta(cls, meta: "CheckpointMeta", quality: RenderQuality = "full",
                  frames: FramesConfig = DEFAULT_FRAMES) -> "RenderSettings":
        return cls.from_config(meta.render, tuple(meta.background), quality, frames)  # type: ignore[arg-type]
