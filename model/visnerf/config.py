"""Typed configuration of the field, the renderer and the trainer. Configs are never mutated."""

import dataclasses
import math
import numbers
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Literal

import torch

FactorStorage = Literal["float32", "float16", "int8"]
FACTOR_STORAGE_DTYPES = {"float32": torch.float32, "float16": torch.float16, "int8": torch.int8}
"""Dtypes the VM planes may be stored in (``FieldConfig.factor_storage``). ``int8`` planes are
row-wise codes with float32 scales (``factor_codec``), and their lines are stored as float16."""


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


def _check_positive(config: object, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        _require(math.isfinite(value) and value > 0, f"{name} must be a finite number above 0, got {value!r}")


def _check_non_negative(config: object, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        _require(math.isfinite(value) and value >= 0, f"{name} must be a finite number of at least 0, got {value!r}")


def _check_at_least(config: object, least: int, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        _require(value >= least, f"{name} must be a whole number of at least {least}, got {value!r}")


def _check_below_one(config: object, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        _require(0.0 <= value < 1.0, f"{name} must be in [0, 1), got {value!r}")


def _check_fractions(config: object, *names: str) -> None:
    """Increasing progress fractions in [0, 1]."""
    for name in names:
        values = getattr(config, name)
        _require(all(0.0 <= v <= 1.0 for v in values), f"{name} must hold fractions in [0, 1], got {values!r}")
        _require(all(b > a for a, b in zip(values, values[1:], strict=False)),
                 f"{name} must increase, got {values!r}")


def _is_whole(value: object) -> bool:
    """An integer (numpy's too), not a bool and not a float that happens to be whole."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _has_type(value: object, annotation: object) -> bool:
    """Whether ``value`` is of a field's annotated type: int, float (an int too), bool, str, or a
    tuple of ints."""
    if typing.get_origin(annotation) is typing.Literal:
        return value in typing.get_args(annotation)
    if typing.get_origin(annotation) is tuple:
        args = typing.get_args(annotation)
        if not isinstance(value, tuple):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_has_type(v, args[0]) for v in value)
        return len(args) == len(value) and all(_has_type(v, a) for v, a in zip(value, args, strict=True))
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return any(_has_type(value, a) for a in typing.get_args(annotation))
    if annotation is type(None):
        return value is None
    if annotation is int:
        return _is_whole(value)
    if annotation is float:
        return isinstance(value, numbers.Real) and not isinstance(value, bool)
    return isinstance(value, annotation) if isinstance(annotation, type) else True


_TYPE_WORDS = {int: "a whole number", float: "a number", bool: "true or false", str: "a string"}


def _check_types(cls: type, values: dict[str, Any]) -> None:
    """Each value has its field's annotated type. ``from_dict`` checks before it builds (a
    configuration read from JSON may hold anything), so that the refusal names the field."""
    for f in dataclasses.fields(cls):
        if f.name in values:
            if typing.get_origin(f.type) is typing.Literal:
                word = "one of " + ", ".join(repr(v) for v in typing.get_args(f.type))
            elif typing.get_origin(f.type) is tuple:
                first = typing.get_args(f.type)[0]
                word = {int: "whole numbers", float: "numbers"}.get(first, "a list")
            else:
                word = _TYPE_WORDS.get(f.type, str(f.type))  # type: ignore[arg-type]
            _require(_has_type(values[f.name], f.type), f"{f.name} must be {word}, got {values[f.name]!r}")


def config_from_dict(cls: type, data: dict[str, Any], what: str) -> Any:
    """``cls`` from a JSON document (a checkpoint's, a run state's, the command line's): every key
    must name a field (``ValueError`` naming the others), JSON lists become tuples, each value is
    checked against its field's type before the configuration's own checks; a field the document
    does not name takes its default. Documents of older formats are migrated before they get here
    (``checkpoint.migrate``)."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"unknown {what} keys {sorted(unknown)}")
    values = {k: tuple(tuple(x) if isinstance(x, list) else x for x in v) if isinstance(v, list) else v
              for k, v in data.items()}
    _check_types(cls, values)
    return cls(**values)


def _check_whole_in(config: object, least: int, most: int, *names: str) -> None:
    """Whole numbers in [least, most]; a tuple field is checked element by element."""
    for name in names:
        value = getattr(config, name)
        items = value if isinstance(value, tuple) else (value,)
        _require(all(_is_whole(v) and least <= v <= most for v in items),
                 f"{name} must be {'whole numbers' if isinstance(value, tuple) else 'a whole number'} "
                 f"in [{least}, {most}], got {value!r}")


def _check_number_in(config: object, least: float, most: float, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        _require(isinstance(value, numbers.Real) and math.isfinite(value) and least <= value <= most,
                 f"{name} must be a finite number in [{least:g}, {most:g}], got {value!r}")


MAX_GRID_RESOLUTION = 4096
"""Largest grid size along one axis (``FieldConfig.resolution``; the recipe's are a few hundred)."""
MAX_PARAM_VALUES = 4096
"""Most training values of one parameter axis."""
MAX_COMPONENTS = 1024
"""Most VM or parameter-vector components."""
MAX_HIDDEN_WIDTH = 4096
"""Widest decoder hidden layer."""
MAX_ENCODING_FREQS = 32
"""Most positional-encoding frequencies."""
MAX_COSINE_POWER = 1024
"""Highest power of a cosine the colour decoder reads (a highlight narrower than 3 degrees)."""
MAX_SAMPLES_LIMIT = 16384
"""Largest ``RenderConfig.max_samples``: a frame costs up to this many samples a ray (1024 by default)."""
STEP_RATIO_RANGE = (0.01, 16.0)
"""Sample spacings (``step_ratio``, ``full_step_ratio``) and the preview's multiplier, in voxels:
a spacing near 0 would ask for unbounded samples a ray, one of many voxels samples nothing."""
PREVIEW_SCALE_RANGE = (1.0 / 16.0, 1.0)
"""Resolution scales of the preview quality."""


@dataclass(frozen=True)
class FieldConfig:
    """Shape of a ViSNeRF field. Everything that fixes a tensor shape lives here."""

    resolution: tuple[int, int, int] = (64, 64, 64)
    """Grid resolution (x, y, z) of the VM planes and lines."""
    n_density_components: int = 16
    """VM components per mode of the density grid."""
    n_appearance_components: int = 48
    """VM components per mode of the appearance grid."""
    param_lengths: tuple[int, ...] = ()
    """One entry per parameter axis: the number of distinct training values (K = len)."""
    n_param_components: int = 4
    """Components of each CP parameter-axis vector."""
    hidden_width: int = 64
    """Hidden layer width of both decoders. 64 rather than 128: the decoders are most of a step's
    and a frame's work, and 64 buys more steps for the same figures, where 32 gains nothing more
    (docs/decisions.md, "Configuration defaults")."""
    pos_encoding_freqs: int = 2
    """Frequencies of the positional encoding of x fed to the density decoder."""
    sh_degree: int = 3
    """Spherical-harmonics degree (0..3) of the view-direction encoding."""
    facing_vectors: int = 0
    """Unit vectors the field learns per point (a linear map of its appearance features) whose
    cosines with the view direction the colour decoder also reads: a surface lit by a light at the
    camera (a headlight) shades as a function of the cosine between its normal and the view, too
    sharp in direction for spherical harmonics. 0: none."""
    level_set_axis: int = -1
    """The parameter axis whose values are isovalues of one scalar field (``param_axes.LevelAxis``):
    the density branch takes no parameter factors along it and subtracts a learnt level of the
    value instead, so every isovalue's surface is a level set of one field and values between the
    training values give the surfaces between. -1: none (every axis scales the features)."""
    level_normal_step: float = 1.0
    """Distance in voxels along each axis of the probes whose values of the level field give its
    normal (``field.level_normal_cosines``; only with a level axis). Closer probes carry the
    field's voxel-scale ripples into the shading (docs/decisions.md, "Configuration defaults")."""
    level_cosine_powers: tuple[int, ...] = (4, 16, 64)
    """Powers of the positive part of the level field's normal cosine that the colour decoder reads
    beside the cosine itself (only with a level axis). An isosurface renderer's highlight is a high
    power of a cosine (Blinn-Phong with a headlight: exponent 40 in the synthetic scenes, half height
    10.6 degrees from the view), too narrow for one ReLU layer to draw from the cosine alone; the
    decoder mixes the powers instead (docs/decisions.md, "Configuration defaults"). (): the
    cosine alone, as checkpoints that do not name this field."""
    density_shift: float = -2.0
    """Added to the raw density before softplus, so that a fresh field is a faint fog (0.13 per world
    unit at a ``density_scale`` of 1): at TensoRF's -10 the photometric gradient behind the density
    decoder is scaled by sigmoid(-10) = 5e-5 and short runs stayed empty."""
    density_scale: float = 1.0
    """Multiplies the softplus of the density decoder's output (per world unit). Opaque surfaces
    need an optical depth of about 10 within a voxel or two, a density of thousands per world unit,
    which a decoder reaches only after many steps at 1; the recipe sets one over the voxel size for
    surface scenes (``training.recipe``), with ``density_shift`` lowered to keep the same fog."""
    init_scale: float = 0.1
    """Standard deviation of the initial VM factors."""
    factor_storage: FactorStorage = "int8"
    """How the checkpoint file stores the VM planes and lines: ``float32``, ``float16`` or ``int8``
    (planes as int8 codes with a float32 scale per row, ``factor_codec``, lines as float16: about
    a quarter of the float32 bytes, frames indistinguishable from float16's: docs/decisions.md,
    "Configuration defaults"). The field computes in float32 either way. Checkpoints that do not
    say hold float32."""

    def __post_init__(self) -> None:
        _check_types(type(self), self.__dict__)
        if len(self.resolution) != 3 or min(self.resolution) < 2:
            raise ValueError(f"resolution must be three sizes >= 2, got {self.resolution}")
        if any(n < 1 for n in self.param_lengths):
            raise ValueError(f"every parameter axis needs at least one value, got {self.param_lengths}")
        _check_at_least(self, 1, "n_param_components")
        if self.n_density_components % self.n_param_components or (
            self.n_appearance_components % self.n_param_components
        ):
            raise ValueError("component counts must be multiples of n_param_components")
        _check_at_least(self, 0, "facing_vectors")
        # a configuration made before the data are read has no axes yet; the field checks the axis against them
        _require(isinstance(self.level_set_axis, int) and self.level_set_axis >= -1
                 and (not self.param_lengths or self.level_set_axis < len(self.param_lengths)),
                 f"level_set_axis must be -1 (none) or one of the {len(self.param_lengths)} parameter axes "
                 f"(0..{len(self.param_lengths) - 1}), got {self.level_set_axis!r}")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0..3, got {self.sh_degree}")
        if self.factor_storage not in FACTOR_STORAGE_DTYPES:
            raise ValueError(f"factor_storage must be one of {sorted(FACTOR_STORAGE_DTYPES)}, got {self.factor_storage!r}")
        _check_at_least(self, 1, "n_density_components", "n_appearance_components", "n_param_components", "hidden_width")
        _check_at_least(self, 0, "pos_encoding_freqs")
        _check_positive(self, "density_scale", "init_scale", "level_normal_step")
        _require(math.isfinite(self.density_shift), f"density_shift must be a finite number, got {self.density_shift!r}")
        _check_whole_in(self, 2, MAX_GRID_RESOLUTION, "resolution")
        _check_whole_in(self, 1, MAX_PARAM_VALUES, "param_lengths")
        _check_whole_in(self, 1, MAX_COMPONENTS, "n_density_components", "n_appearance_components", "n_param_components")
        _check_whole_in(self, 1, MAX_HIDDEN_WIDTH, "hidden_width")
        _check_whole_in(self, 0, MAX_ENCODING_FREQS, "pos_encoding_freqs")
        _check_whole_in(self, 1, MAX_COSINE_POWER, "level_cosine_powers")

    @property
    def n_params(self) -> int:
        return len(self.param_lengths)

    def with_resolution(self, resolution: tuple[int, int, int]) -> "FieldConfig":
        return dataclasses.replace(self, resolution=tuple(int(r) for r in resolution))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "FieldConfig":
        return config_from_dict(cls, data, "field configuration")


@dataclass(frozen=True)
class RenderConfig:
    """How rays are marched at inference and in training."""

    step_ratio: float = 1.647
    """Sample spacing of training in voxels of the grid (the world spacing follows the grid as it
    is upsampled); the exhaustive reference samples at the finer of this and half a voxel
    (``renderer.exhaustive_step_ratio``), the preview at that times ``preview_step_factor``. With
    the recipe's voxels (``training.recipe``, 0.93 of a pixel at the content) samples land about
    1.5 pixels apart, the spacing the Nyx record trained at (bench/results/nyx_history.md)."""
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
    (bench/results/full_quality_threshold.md; docs/decisions.md, "Configuration defaults").
    Checkpoints from before store ``full_weight_threshold``, a threshold per sample, which is not
    read: they take this default."""
    early_stop_eps: float = 1e-4
    """Rays stop once transmittance falls below this (inference)."""
    preview_scale: float = 0.5
    """Resolution scale of the preview quality."""
    preview_step_factor: float = 2.0
    """Step multiplier of the preview quality."""

    def __post_init__(self) -> None:
        _check_types(type(self), self.__dict__)
        _check_positive(self, "step_ratio", "full_step_ratio", "preview_step_factor")
        _check_at_least(self, 1, "max_samples")
        _check_below_one(self, "occupancy_threshold", "weight_threshold", "full_weight_threshold_per_voxel", "early_stop_eps")
        _require(0.0 < self.preview_scale <= 1.0, f"preview_scale must be in (0, 1], got {self.preview_scale!r}")
        _check_whole_in(self, 1, MAX_SAMPLES_LIMIT, "max_samples")
        _check_number_in(self, *STEP_RATIO_RANGE, "step_ratio", "full_step_ratio", "preview_step_factor")
        _check_number_in(self, *PREVIEW_SCALE_RANGE, "preview_scale")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "RenderConfig":
        return config_from_dict(cls, data, "render configuration")


DEFAULT_ITERATIONS = 30_000
"""Steps of a run given neither ``TrainConfig.iterations`` nor a time budget (its docstring says
30,000 too, for ``--help``)."""


@dataclass(frozen=True)
class TrainConfig:
    """The training recipe. Milestones are fractions of the run (iterations or wall time)."""

    iterations: int | None = None
    """Steps after which the run ends; none: 30,000 without a time budget, and under one the budget
    alone ends the run. A fixed limit would end a budgeted run early on a fast machine: Nyx makes
    30,000 steps in about 24 of its 60 minutes on a 2-core Zen 5 EPYC
    (bench/results/nyx_middle_hour). With both, the run ends at whichever comes first
    (``step_limit``)."""
    time_budget_s: float | None = None
    """Seconds of training (validation excluded). Progress is the larger of the time fraction and
    the step fraction (``step_limit``); the schedule's milestones are fractions of it."""
    batch_rays: int = 2048
    """Rays per iteration: half the paper's 4096; more, noisier steps fit faster on a CPU
    (docs/decisions.md, "Configuration defaults")."""
    micro_batch_rays: int = 4096
    """Most rays rendered and back-propagated together within an iteration; the step is the same
    for any value (``micro_batch_samples`` bounds the memory)."""
    micro_batch_samples: int = 131072
    """Most samples evaluated (in the box, in occupied cells, in front of opaque content) per
    micro-batch: bounds activation memory (one 4096-ray step of a fresh Nyx-sized fog: +996 MB at
    131072, +382 MB at 32768) while a late step of 2048 rays stays one micro-batch."""
    trim_every: int = 25
    """Iterations between returns of freed heap memory to the system (bounds resident memory)."""
    lr_factors: float = 0.02
    """Adam learning rate of grid factors and parameter vectors."""
    lr_networks: float = 2e-3
    """Adam learning rate of the decoders: twice the paper's 0.001 (docs/decisions.md,
    "Configuration defaults")."""
    betas: tuple[float, float] = (0.9, 0.99)
    """Adam's decay rates of the first and second moment estimates."""
    lr_decay_ratio: float = 0.1
    """Learning rates decay exponentially to this fraction at the end of the run."""
    resolution_init: int = 64
    """Voxels per axis (cube root of the voxel count) at the start."""
    resolution_final: int = 120
    """Voxels per axis (cube root of the voxel count) at the end. ``visnerf train`` chooses it
    from the pixel size at the content (``training.recipe``); 120 is for callers that do not."""
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
    keeps a ring of ``training.recipe.SURFACE_REFINE_DILATION`` cells for opaque surfaces, which
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
    the hull's). ``visnerf train`` grows it by ``training.recipe.SURFACE_CARVE_DILATION`` cells for
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
    the density, and thin filaments need it sharp (docs/decisions.md, "Configuration defaults";
    the recipe sets it for opaque surfaces)."""
    tv_weight_appearance: float = 0.0
    """Total variation on the appearance factors: none, the fit is limited by capacity, not noise
    (docs/decisions.md, "Configuration defaults"; the recipe sets it for opaque surfaces)."""
    level_curvature_weight: float = 4.0
    """Weight of the curvature prior of a level axis's field ``g`` (``regularizers.level_curvature``:
    its squared second difference along random directions at random points of the box, over the
    squared span of the levels); nothing without a level axis. The images pin ``g`` only at the
    training surfaces, and the surfaces between training values are its level sets; a ``g`` whose
    slope changes smoothly carries the slope across each band, where a merely smooth ``g`` rises
    evenly between two surfaces and keeps a shrinking blob's arms too long (docs/decisions.md,
    "Configuration defaults")."""
    level_spacing_weight: float = 0.1
    """Weight of the bound on how much a level axis's neighbouring bands differ in slope
    (``regularizers.level_spacing``, nothing within ``level_spacing_ratio``). Without it an opaque
    training surface's level can drift off on fading gradients until the whole occupancy grid lies
    inside that surface; a pull toward even bands instead of a bound fits held-out views far worse.
    What pushed the level is the grid's edge cutting the surface
    (``training.recipe.SURFACE_CARVE_DILATION`` and ``SURFACE_REFINE_DILATION`` answer it;
    docs/decisions.md, "Configuration defaults")."""
    level_spacing_ratio: float = 4.0
    """Factor by which neighbouring bands' slopes may differ at no cost (trained tangle_iso fields
    have 1.3 to 1.5)."""
    level_curvature_points: int = 1024
    """Random points a step for ``level_curvature_weight``: more cost steps and gained nothing
    (docs/decisions.md, "Configuration defaults")."""
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
    by a factor of e. 0: off (docs/decisions.md, "Configuration defaults")."""
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
    random_background: bool = False
    """Composite on a random colour per ray in training (useful when content touches the background)."""

    @property
    def step_limit(self) -> int | None:
        """Steps after which the run ends; None: only the time budget ends it."""
        if self.iterations is not None:
            return self.iterations
        return None if self.time_budget_s is not None else DEFAULT_ITERATIONS

    def __post_init__(self) -> None:
        _require(self.iterations is None or (_is_whole(self.iterations) and self.iterations >= 1),
                 f"iterations must be at least 1, or none (the default), got {self.iterations!r}")
        for name in ("batch_rays", "micro_batch_rays", "micro_batch_samples"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.time_budget_s is not None and not (math.isfinite(self.time_budget_s) and self.time_budget_s > 0):
            raise ValueError(f"time_budget_s must be a finite number of seconds above 0 (or None), got {self.time_budget_s}")
        if self.occupancy_refine_dilation < 0:
            raise ValueError(f"occupancy_refine_dilation must be >= 0 cells, got {self.occupancy_refine_dilation}")
        if not 0.0 < self.density_grad_keep <= 1.0:
            raise ValueError(f"density_grad_keep must be in (0, 1], got {self.density_grad_keep}")
        if not (math.isfinite(self.weight_average_span) and self.weight_average_span >= 0.0):
            raise ValueError(f"weight_average_span must be a progress fraction >= 0 (0: off), got {self.weight_average_span}")
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
        _check_at_least(self, 1, "trim_every", "occupancy_max_settings", "validate_max_images")
        _check_at_least(self, 2, "resolution_init", "resolution_final", "occupancy_resolution", "carve_resolution")
        _check_at_least(self, 0, "occupancy_min_iterations", "l1_switch_iteration")
        _check_at_least(self, 1, "level_curvature_points")
        _check_positive(self, "lr_factors", "lr_networks", "validate_every_s")
        _require(0.0 < self.lr_decay_ratio <= 1.0, f"lr_decay_ratio must be in (0, 1], got {self.lr_decay_ratio!r}")
        _require(len(self.betas) == 2 and all(0.0 <= b < 1.0 for b in self.betas),
                 f"betas must be two numbers in [0, 1), got {self.betas!r}")
        _check_non_negative(self, "checkpoint_every_s", "l1_weight_initial", "l1_weight_rest", "param_l1_weight",
                            "tv_weight_density", "tv_weight_appearance", "tv_weight_params",
                            "level_curvature_weight", "level_spacing_weight")
        _check_below_one(self, "stop_eps")
        _require(0.0 <= self.carve_min_seen_fraction <= 1.0,
                 f"carve_min_seen_fraction must be in [0, 1], got {self.carve_min_seen_fraction!r}")
        _require(0 <= self.carve_dilation <= 16, f"carve_dilation must be in 0..16, got {self.carve_dilation!r}")
        _require(0 <= self.carve_tolerance <= 255, f"carve_tolerance must be in 0..255, got {self.carve_tolerance!r}")
        _check_fractions(self, "upsample_at", "occupancy_at", "occupancy_refine_at")
        _require(self.level_spacing_ratio > 1.0, f"level_spacing_ratio must be > 1, got {self.level_spacing_ratio!r}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "TrainConfig":
        """The configuration a checkpoint's ``provenance.recipe`` or a run state records
        (``config_from_dict``: older checkpoints recorded a subset, the rest take their defaults)."""
        return config_from_dict(cls, data, "training configuration")


@dataclass(frozen=True)
class HoldoutConfig:
    """Which training frames are held out for validation."""

    views: tuple[int, ...] = ()
    """Indices of views (position in the icosphere order) held out at every parameter setting."""
    settings: tuple[tuple[float, ...], ...] = field(default_factory=tuple)
    """Whole parameter settings held out from all views."""
    axis_values: tuple[tuple[int, float], ...] = field(default_factory=tuple)
    """``(axis, value)`` pairs: every frame whose parameter ``axis`` (index among the dataset's
    varying parameters, in their order) has ``value`` is held out, at all views and all values of
    the other axes. Holding out an axis' middle value leaves training only the values around it, so
    validation measures the model between sampled values, as a test path between them does."""

    def __post_init__(self) -> None:
        for view in self.views:
            _require(_is_whole(view) and view >= 0,
                     f"held-out view {view!r} must be a whole number of at least 0")
        for pair in self.axis_values:
            _require(isinstance(pair, tuple) and len(pair) == 2,
                     f"held-out axis value {pair!r} must be a pair (axis index, value)")
            axis, value = pair
            _require(_is_whole(axis) and axis >= 0,
                     f"held-out axis value {pair!r}: the axis must be an index of at least 0, got {axis!r}")
            _require(isinstance(value, numbers.Real) and math.isfinite(value),
                     f"held-out axis value {pair!r}: the value must be a finite number, got {value!r}")
