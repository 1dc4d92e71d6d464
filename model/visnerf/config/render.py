"""``RenderConfig``: how rays are marched at inference and in training."""

import dataclasses
from dataclasses import dataclass
from typing import Any

from visnerf.config.checks import (
    check_at_least,
    check_below_one,
    check_number_in,
    check_positive,
    check_types,
    check_whole_in,
    config_from_dict,
    require,
)

MAX_SAMPLES_LIMIT = 16384
"""Largest ``RenderConfig.max_samples``: a frame costs up to this many samples a ray (1024 by default)."""
STEP_RATIO_RANGE = (0.01, 16.0)
"""Sample spacings (``step_ratio``, ``full_step_ratio``) and the preview's multiplier, in voxels:
a spacing near 0 would ask for unbounded samples a ray, one of many voxels samples nothing."""
PREVIEW_SCALE_RANGE = (1.0 / 16.0, 1.0)
"""Resolution scales of the preview quality."""


@dataclass(frozen=True)
class RenderConfig:
    """How rays are marched at inference and in training."""

    step_ratio: float = 1.647
    """Sample spacing of training in voxels of the grid (the world spacing follows the grid as it
    is upsampled); the exhaustive reference samples at the finer of this and half a voxel
    (``renderer.exhaustive_step_ratio``), the preview at that times ``preview_step_factor``. With
    the recipe's voxels (``training.recipe``, 0.93 of a pixel at the content) samples land about
    1.5 pixels apart, the spacing the Nyx record trained at (docs/decisions.md#recipe.voxel_per_pixel)."""
    full_step_ratio: float = 0.75
    """Sample spacing of full-quality inference frames in voxels (stored with each checkpoint):
    training ends by choosing the coarsest spacing whose held-out frames (training frames when none
    are held out) are within 0.05 dB of exhaustive ones (``evaluation.spacing``, ``visnerf
    calibrate``); this default is for checkpoints that stored none."""
    max_samples: int = 1024
    """Upper bound on samples per ray (at most ``MAX_SAMPLES_LIMIT``)."""
    bf16: bool = True
    """Full and preview frames run the decoders' matrix products in bfloat16 where the device has
    bf16 matrix instructions (AMX or AVX512-BF16 on x86; ``runtime.bf16_native``), as training does."""
    occupancy_threshold: float = 1e-4
    """Alpha below which an occupancy cell counts as empty."""
    weight_threshold: float = 1e-4
    """Training samples whose compositing weight is below this skip colour decoding."""
    full_weight_threshold_per_voxel: float = 2e-3
    """Full-quality and preview frames decode colour only for samples whose compositing weight
    exceeds this times the sample spacing in voxels; the weight of the others takes the mean colour
    of the ray's decoded samples (``renderer._unshaded_gain``). A sample's weight in a translucent
    medium grows with the spacing, so a threshold per sample skipped more of the medium the finer
    the frame was sampled; per voxel, it skips the same share at every spacing
    (docs/decisions.md#render.full_weight_threshold).
    Checkpoints from before store ``full_weight_threshold``, a threshold per sample, which is not
    read: they take this default."""
    early_stop_eps: float = 1e-4
    """Rays stop once transmittance falls below this (inference)."""
    preview_scale: float = 0.5
    """Resolution scale of the preview quality."""
    preview_step_factor: float = 2.0
    """Step multiplier of the preview quality."""

    def __post_init__(self) -> None:
        check_types(type(self), self.__dict__)
        check_positive(self, "step_ratio", "full_step_ratio", "preview_step_factor")
        check_at_least(self, 1, "max_samples")
        check_below_one(self, "occupancy_threshold", "weight_threshold", "full_weight_threshold_per_voxel",
                        "early_stop_eps")
        require(0.0 < self.preview_scale <= 1.0, f"preview_scale must be in (0, 1], got {self.preview_scale!r}")
        check_whole_in(self, 1, MAX_SAMPLES_LIMIT, "max_samples")
        check_number_in(self, *STEP_RATIO_RANGE, "step_ratio", "full_step_ratio", "preview_step_factor")
        check_number_in(self, *PREVIEW_SCALE_RANGE, "preview_scale")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "RenderConfig":
        return config_from_dict(cls, data, "render configuration")
