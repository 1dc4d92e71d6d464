"""``FieldConfig``: the shape of a ViSNeRF field (everything that fixes a tensor shape)."""

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Literal

import torch

from visnerf.config.checks import (
    check_at_least,
    check_positive,
    check_types,
    check_whole_in,
    config_from_dict,
    require,
)

FactorStorage = Literal["float32", "float16", "int8"]
FACTOR_STORAGE_DTYPES = {"float32": torch.float32, "float16": torch.float16, "int8": torch.int8}
"""Dtypes the VM planes may be stored in (``FieldConfig.factor_storage``). ``int8`` planes are
row-wise codes with float32 scales (``factor_codec``), and their lines are stored as float16."""


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
    (docs/decisions.md#field.hidden_width)."""
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
    field's voxel-scale ripples into the shading (docs/decisions.md#field.level_normal_step)."""
    level_cosine_powers: tuple[int, ...] = (4, 16, 64)
    """Powers of the positive part of the level field's normal cosine that the colour decoder reads
    beside the cosine itself (only with a level axis). An isosurface renderer's highlight is a high
    power of a cosine (Blinn-Phong with a headlight: exponent 40 in the synthetic scenes, half height
    10.6 degrees from the view), too narrow for one ReLU layer to draw from the cosine alone; the
    decoder mixes the powers instead (docs/decisions.md#field.level_cosine_powers). (): the
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
    a quarter of the float32 bytes, frames indistinguishable from float16's:
    docs/decisions.md#field.factor_storage). The field computes in float32 either way. Checkpoints
    that do not say hold float32."""

    def __post_init__(self) -> None:
        check_types(type(self), self.__dict__)
        if len(self.resolution) != 3 or min(self.resolution) < 2:
            raise ValueError(f"resolution must be three sizes >= 2, got {self.resolution}")
        if any(n < 1 for n in self.param_lengths):
            raise ValueError(f"every parameter axis needs at least one value, got {self.param_lengths}")
        check_at_least(self, 1, "n_param_components")
        if self.n_density_components % self.n_param_components or (
            self.n_appearance_components % self.n_param_components
        ):
            raise ValueError("component counts must be multiples of n_param_components")
        check_at_least(self, 0, "facing_vectors")
        # a configuration made before the data are read has no axes yet; the field checks the axis against them
        require(isinstance(self.level_set_axis, int) and self.level_set_axis >= -1
                 and (not self.param_lengths or self.level_set_axis < len(self.param_lengths)),
                 f"level_set_axis must be -1 (none) or one of the {len(self.param_lengths)} parameter axes "
                 f"(0..{len(self.param_lengths) - 1}), got {self.level_set_axis!r}")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0..3, got {self.sh_degree}")
        if self.factor_storage not in FACTOR_STORAGE_DTYPES:
            raise ValueError(f"factor_storage must be one of {sorted(FACTOR_STORAGE_DTYPES)}, "
                             f"got {self.factor_storage!r}")
        check_at_least(self, 1, "n_density_components", "n_appearance_components", "n_param_components", "hidden_width")
        check_at_least(self, 0, "pos_encoding_freqs")
        check_positive(self, "density_scale", "init_scale", "level_normal_step")
        require(math.isfinite(self.density_shift), f"density_shift must be a finite number, got {self.density_shift!r}")
        check_whole_in(self, 2, MAX_GRID_RESOLUTION, "resolution")
        check_whole_in(self, 1, MAX_PARAM_VALUES, "param_lengths")
        check_whole_in(self, 1, MAX_COMPONENTS, "n_density_components", "n_appearance_components", "n_param_components")
        check_whole_in(self, 1, MAX_HIDDEN_WIDTH, "hidden_width")
        check_whole_in(self, 0, MAX_ENCODING_FREQS, "pos_encoding_freqs")
        check_whole_in(self, 1, MAX_COSINE_POWER, "level_cosine_powers")

    @property
    def n_params(self) -> int:
        return len(self.param_lengths)

    def with_resolution(self, resolution: tuple[int, int, int]) -> "FieldConfig":
        return dataclasses.replace(self, resolution=(int(resolution[0]), int(resolution[1]), int(resolution[2])))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "FieldConfig":
        return config_from_dict(cls, data, "field configuration")
