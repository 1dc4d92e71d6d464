"""``TrainConfig``: the training recipe (milestones as fractions of the run)."""

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from visnerf.config.checks import (
    check_at_least,
    check_below_one,
    check_fractions,
    check_non_negative,
    check_positive,
    config_from_dict,
    is_whole,
    require,
)

DEFAULT_ITERATIONS = 30_000
"""Steps of a run given neither ``TrainConfig.iterations`` nor a time budget (its docstring says
30,000 too, for ``--help``)."""


@dataclass(frozen=True)
class TrainConfig:
    """The training recipe. Milestones are fractions of the run (iterations or wall time)."""

    iterations: int | None = None
    """Steps after which the run ends; none: 30,000 without a time budget, and under one the budget
    alone ends the run: a fixed limit would end a budgeted run early on a fast machine
    (docs/decisions.md#train.time_budget). With both, the run ends at whichever comes first
    (``step_limit``)."""
    time_budget_s: float | None = None
    """Seconds of training (validation excluded). Progress is the larger of the time fraction and
    the step fraction (``step_limit``); the schedule's milestones are fractions of it."""
    batch_rays: int = 2048
    """Rays per iteration: half the paper's 4096; more, noisier steps fit faster on a CPU
    (docs/decisions.md#train.batch_rays)."""
    micro_batch_rays: int = 4096
    """Most rays rendered and back-propagated together within an iteration; the step is the same
    for any value (``micro_batch_samples`` bounds the memory)."""
    micro_batch_samples: int = 131072
    """Most samples evaluated (in the box, in occupied cells, in front of opaque content) per
    micro-batch: bounds the activations of an early step through fog while a late step of 2048
    rays stays one micro-batch (docs/decisions.md#train.micro_batch_samples)."""
    trim_every: int = 25
    """Iterations between returns of freed heap memory to the system (bounds resident memory)."""
    lr_factors: float = 0.02
    """Adam learning rate of grid factors and parameter vectors."""
    lr_networks: float = 2e-3
    """Adam learning rate of the decoders: twice the paper's 0.001 (docs/decisions.md#train.lr_networks)."""
    betas: tuple[float, float] = (0.9, 0.99)
    """Adam's decay rates of the first and second moment estimates."""
    lr_decay_ratio: float = 0.1
    """Learning rates decay exponentially to this fraction at the end of the run."""
    resolution_init: int = 64
    """Voxels per axis (cube root of the voxel count) at the start."""
    resolution_final: int = 120
    """Voxels per axis (cube root of the voxel count) at the end. ``visnerf train`` chooses it
    from the pixel size at the content (``training.recipe``); 120 is for callers that do not."""
    rays_per_voxel: float = 0.0
    """Under a time budget, at each upsampling the final grid is cut to at most the rays the budget
    will see over this many voxels (``training.grid_budget``), never under the grid reached; 0
    keeps ``resolution_final``. ``visnerf train`` sets it unless the grid is given."""
    upsample_at: tuple[float, ...] = (0.067, 0.1, 0.133, 0.183, 0.233)
    """Progress fractions at which planes and lines are upsampled (log-spaced resolutions)."""
    occupancy_at: tuple[float, ...] = (0.067, 0.133)
    """Progress fractions at which the occupancy mask is rebuilt (the first also shrinks the box)."""
    occupancy_refine_at: tuple[float, ...] = (0.25, 0.5, 0.75)
    """Progress fractions, after the ``occupancy_at`` milestones, at which the occupancy grid is
    rebuilt from the density within itself (``Trainer.refine_occupancy``: cells leave as the
    density sparsens, none join), so that later steps sample fewer empty cells."""
    occupancy_refine_dilation: int = 0
    """Cells by which a refined grid (``occupancy_refine_at`` and the end of training) is grown
    around the cells that hold content. The ``occupancy_at`` grids keep one cell, room for content
    still forming; once formed, 0 leaves out a ring of near-empty cells that training would keep
    sampling (Nyx: 2.6 times fewer density samples a step, 1.20 times faster). ``visnerf train``
    keeps a ring of ``config.recipe.SurfaceRecipe.refine_dilation`` cells for opaque surfaces, which
    the grid's edge would otherwise cut."""
    occupancy_min_iterations: int = 300
    """Occupancy milestones wait for at least this many iterations (a time budget on a busy machine
    would otherwise reach them before the density has formed)."""
    occupancy_resolution: int = 96
    """Cells per axis of the occupancy grid (at most)."""
    occupancy_max_settings: int = 64
    """Parameter settings evaluated for the occupancy union (all training settings if fewer)."""
    carve: bool = True
    """Carve empty space from the training images before the first iteration (see data/carving.py):
    the box shrinks to the visual hull and samples are taken only inside it from the start."""
    carve_resolution: int = 64
    """Cells per axis of the carved grid."""
    carve_dilation: int = 0
    """Cells of the carved grid by which it is grown before training samples in it (the box stays
    the hull's). ``visnerf train`` grows it by ``config.recipe.SurfaceRecipe.carve_dilation`` cells for
    opaque surfaces, which can otherwise settle on the hull's edge."""
    carve_tolerance: int = 2
    """Largest channel difference (0-255) from the background that still counts as background."""
    carve_min_seen_fraction: float = 0.0
    """A carved cell must be in the frame of at least this fraction of its setting's views (0: of
    one view). ``visnerf train`` chooses 0.75 where every image frames its content whole and 0
    where content touches an image border (``training.recipe``): a few views that see a far corner
    of the camera box all look through it at the content, so at 0 such corners survive carving
    (on Nyx they stretch the box from +-0.19 to +-0.31 on two axes; ``data/carving.py``)."""
    mixed_precision: bool = True
    """Decoder matrix products in bfloat16 where the device supports it (weights stay float32)."""
    l1_weight_initial: float = 1e-4
    """L1 weight on the density factors (sparsity) until ``l1_switch_iteration``."""
    l1_weight_rest: float = 1e-5
    """L1 weight on the density factors after ``l1_switch_iteration``."""
    l1_switch_iteration: int = 2000
    """Iteration after which the L1 weight drops to ``l1_weight_rest``."""
    param_l1_weight: float = 1e-4
    """L1 pull of the parameter vectors toward 1."""
    tv_weight_density: float = 0.0
    """Total variation on the density factors: none, as in the paper's Nyx configuration; it smooths
    the density, and thin filaments need it sharp (docs/decisions.md#train.tv_weights;
    the recipe sets it per content)."""
    tv_weight_appearance: float = 0.0
    """Total variation on the appearance factors: none, the fit is limited by capacity, not noise
    (docs/decisions.md#train.tv_weights; the recipe sets it per content)."""
    level_curvature_weight: float = 4.0
    """Weight of the curvature prior of a level axis's field ``g`` (``regularizers.level_curvature``:
    its squared second difference along random directions at random points of the box, over the
    squared span of the levels); nothing without a level axis. The images pin ``g`` only at the
    training surfaces, and the surfaces between training values are its level sets; a ``g`` whose
    slope changes smoothly carries the slope across each band, where a merely smooth ``g`` rises
    evenly between two surfaces and keeps a shrinking blob's arms too long
    (docs/decisions.md#train.level_curvature_weight)."""
    level_spacing_weight: float = 0.1
    """Weight of the bound on how much a level axis's neighbouring bands differ in slope
    (``regularizers.level_spacing``, nothing within ``level_spacing_ratio``). Without it an opaque
    training surface's level can drift off on fading gradients until the whole occupancy grid lies
    inside that surface; a pull toward even bands instead of a bound fits held-out views far worse.
    What pushed the level is the grid's edge cutting the surface
    (``config.recipe.SurfaceRecipe.carve_dilation`` and ``refine_dilation`` answer it;
    docs/decisions.md#train.level_spacing_weight)."""
    level_spacing_ratio: float = 4.0
    """Factor by which neighbouring bands' slopes may differ at no cost (trained tangle_iso fields
    have 1.3 to 1.5)."""
    level_curvature_points: int = 1024
    """Random points a step for ``level_curvature_weight``: more cost steps and gained nothing
    (docs/decisions.md#train.level_curvature_points)."""
    tv_weight_params: float = 0.01
    """Total variation on the parameter vectors (smoothness along each parameter axis)."""
    stop_eps: float = 1e-4
    """Samples a ray reaches with transmittance below this are dropped from a training step
    (``renderer.drop_occluded``): behind an opaque surface they cost a full differentiable pass
    and change the render by less than this. 0: every sample is shaded."""
    density_grad_keep: float = 0.125
    """Fraction of the near-empty samples (alpha below ``density_grad_floor``) whose density a
    step back-propagates, their gradient scaled by its inverse: an unbiased estimate of the full
    gradient at a fraction of the backward work (``rendering.density_gradients``). 1: every sample."""
    density_grad_floor: float = 1e-4
    """Alpha over one sample's interval below which a sample counts as near-empty (the occupancy
    grid's and the colour pass's threshold)."""
    colour_weight_floor: float = 0.0
    """Samples of weight below this are coloured in a training step only at random, with
    probability weight / floor, and then count with the floor's weight: an unbiased estimate of the
    rendered colour and its gradient that skips most of a faint fog's samples
    (``rendering.colour_sampling``). 0: every sample above the renderer's weight threshold."""
    silhouette_ray_fraction: float = 0.0
    """Share of each batch's rays drawn from the training images' silhouette band (pixels within
    one pixel of a boundary between background and content, ``training.ray_batches``) instead of
    from every pixel. An opaque surface's error lies almost all in that band. 0: every pixel alike."""
    weight_average_span: float = 0.03
    """Return the parameters' moving average over the end of the run instead of their last values
    (``training/weight_average.py``): the span of progress over which an old value's weight falls
    by a factor of e. 0: off (docs/decisions.md#train.weight_average_span)."""
    weight_average_from: float = 0.5
    """Progress fraction from which the average is kept; it restarts if the grid is upsampled
    later (a resumed run continues it from its run state)."""
    weight_average_every: int = 4
    """Steps between updates of the average (each is a pass over every parameter)."""
    validate_every_s: float = 120.0
    """Seconds of training between validations."""
    checkpoint_every_s: float = 300.0
    """Seconds of training between writes of the run state (``training/run_state.py``), for a run
    that has a file for it (``visnerf train`` keeps it beside ``--out``): a job killed outright
    loses at most this much. 0: written only when the run is stopped by SIGTERM or Ctrl-C."""
    validate_max_images: int = 8
    """Held-out frames rendered at each validation (evenly chosen)."""
    choose_full_spacing: bool = True
    """At the end of training, choose the checkpoint's full-quality sample spacing
    (``evaluation.spacing``) on the validation frames, or on training frames where none are held
    out."""
    seed: int = 0
    """Seed of the ray draws, the sample jitter and the field's initial factors."""

    @property
    def step_limit(self) -> int | None:
        """Steps after which the run ends; None: only the time budget ends it."""
        if self.iterations is not None:
            return self.iterations
        return None if self.time_budget_s is not None else DEFAULT_ITERATIONS

    def __post_init__(self) -> None:
        require(self.iterations is None or (is_whole(self.iterations) and self.iterations >= 1),
                 f"iterations must be at least 1, or none (the default), got {self.iterations!r}")
        for name in ("batch_rays", "micro_batch_rays", "micro_batch_samples"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.time_budget_s is not None and not (math.isfinite(self.time_budget_s) and self.time_budget_s > 0):
            raise ValueError("time_budget_s must be a finite number of seconds above 0 (or None), "
                             f"got {self.time_budget_s}")
        if self.occupancy_refine_dilation < 0:
            raise ValueError(f"occupancy_refine_dilation must be >= 0 cells, got {self.occupancy_refine_dilation}")
        if not 0.0 < self.density_grad_keep <= 1.0:
            raise ValueError(f"density_grad_keep must be in (0, 1], got {self.density_grad_keep}")
        if not (math.isfinite(self.weight_average_span) and self.weight_average_span >= 0.0):
            raise ValueError("weight_average_span must be a progress fraction >= 0 (0: off), "
                             f"got {self.weight_average_span}")
        if not 0.0 <= self.weight_average_from <= 1.0:
            raise ValueError(f"weight_average_from must be in [0, 1], got {self.weight_average_from}")
        if self.weight_average_every < 1:
            raise ValueError(f"weight_average_every must be at least 1 step, got {self.weight_average_every}")
        if not 0.0 <= self.silhouette_ray_fraction < 1.0:
            raise ValueError(f"silhouette_ray_fraction must be in [0, 1), got {self.silhouette_ray_fraction}")
        if not 0.0 <= self.colour_weight_floor < 1.0:
            raise ValueError(f"colour_weight_floor must be in [0, 1), got {self.colour_weight_floor}")
        if not 0.0 <= self.density_grad_floor < 1.0:
            raise ValueError(f"density_grad_floor must be in [0, 1), got {self.density_grad_floor}")
        check_at_least(self, 1, "trim_every", "occupancy_max_settings", "validate_max_images")
        check_at_least(self, 2, "resolution_init", "resolution_final", "occupancy_resolution", "carve_resolution")
        check_at_least(self, 0, "occupancy_min_iterations", "l1_switch_iteration")
        check_at_least(self, 1, "level_curvature_points")
        check_positive(self, "lr_factors", "lr_networks", "validate_every_s")
        require(0.0 < self.lr_decay_ratio <= 1.0, f"lr_decay_ratio must be in (0, 1], got {self.lr_decay_ratio!r}")
        require(len(self.betas) == 2 and all(0.0 <= b < 1.0 for b in self.betas),
                 f"betas must be two numbers in [0, 1), got {self.betas!r}")
        require(math.isfinite(self.rays_per_voxel) and self.rays_per_voxel >= 0.0,
                f"rays_per_voxel must be a finite number >= 0 (0: off), got {self.rays_per_voxel!r}")
        check_non_negative(self, "checkpoint_every_s", "l1_weight_initial", "l1_weight_rest", "param_l1_weight",
                            "tv_weight_density", "tv_weight_appearance", "tv_weight_params",
                            "level_curvature_weight", "level_spacing_weight")
        check_below_one(self, "stop_eps")
        require(0.0 <= self.carve_min_seen_fraction <= 1.0,
                 f"carve_min_seen_fraction must be in [0, 1], got {self.carve_min_seen_fraction!r}")
        require(0 <= self.carve_dilation <= 16, f"carve_dilation must be in 0..16, got {self.carve_dilation!r}")
        require(0 <= self.carve_tolerance <= 255, f"carve_tolerance must be in 0..255, got {self.carve_tolerance!r}")
        check_fractions(self, "upsample_at", "occupancy_at", "occupancy_refine_at")
        require(self.level_spacing_ratio > 1.0, f"level_spacing_ratio must be > 1, got {self.level_spacing_ratio!r}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "TrainConfig":
        """The configuration a checkpoint's ``provenance.recipe`` or a run state records
        (``config_from_dict``: older checkpoints recorded a subset, the rest take their defaults)."""
        return config_from_dict(cls, data, "training configuration")
