"""``FramesConfig``: how this machine cuts a frame into work and which per-setting occupancy grids
it keeps. The machine's, not the model's: no checkpoint stores it; the server (``Settings``),
``visnerf render`` and ``visnerf animate`` set it."""

from dataclasses import dataclass

from visnerf.config.checks import check_types, check_whole_in, require

MAX_CHUNK_RAYS = 1 << 20
"""Largest ``chunk_rays``: a chunk's buffers grow with its rays times its segment."""
MAX_SEGMENT_SAMPLES = 4096
"""Largest ``segment_samples`` and ``first_segment_samples``."""


@dataclass(frozen=True)
class FramesConfig:
    """Chunks of rays and segments of samples of a frame, and the cache of per-setting grids."""

    chunk_rays: int = 4096
    """Rays per chunk of a frame; on the CPU the chunks go one per thread (a GPU takes a multiple,
    ``runtime.batch_factor``)."""
    segment_samples: int = 128
    """Samples marched per segment before finished rays are dropped; 4096 rays by 128 samples was
    the fastest chunk (docs/decisions.md#frames.chunks)."""
    first_segment_samples: int = 16
    """Samples in a ray's first segment; each later one doubles, up to ``segment_samples``: rays
    that turn opaque early (surfaces) stop without marching a whole long segment."""
    setting_grids: int = 8
    """Per-setting occupancy grids kept, least recently used dropped first; 0 builds none
    (``rendering.setting_occupancy``)."""
    setting_grid_after: int = 3
    """Full-quality frames at one parameter setting before its grid is built: 1 builds at once. The
    web client asks twice when a view settles (the training images' size, then the view's), so 3
    builds at the next view of a setting a slider stopped at, not beside the frame at the view's
    size, which it slowed (docs/decisions.md#frames.setting_grids)."""
    setting_grid_samples: int = 2
    """Density samples per cell and axis of a setting grid (as the union grid is built)."""
    refine_spacing: int = 4
    """Largest spacing, in pixels, of the lattice a full-quality frame is first marched on where
    a voxel spans that many pixels (``rendering.refine``); 1 marches every pixel."""
    refine_spread: float = 12.0 / 255.0
    """A lattice cell whose four corners differ by more than this in some channel (colours in
    [0, 1]) has its inner pixels marched; the others are blended from the corners. 12 levels of
    255: the refined frame stays closer to every pixel marched than the fast frame is to the plain
    renderer, and 16 let a cell's error grow (docs/decisions.md#frames.refine)."""

    def __post_init__(self) -> None:
        check_types(type(self), self.__dict__)
        check_whole_in(self, 1, MAX_CHUNK_RAYS, "chunk_rays")
        check_whole_in(self, 1, MAX_SEGMENT_SAMPLES, "segment_samples", "first_segment_samples")
        check_whole_in(self, 0, 1024, "setting_grids")
        check_whole_in(self, 1, 1024, "setting_grid_after")
        check_whole_in(self, 1, 8, "setting_grid_samples")
        require(self.refine_spacing in (1, 2, 4, 8, 16),
                f"refine_spacing must be 1, 2, 4, 8 or 16, got {self.refine_spacing}")
        require(0.0 <= self.refine_spread <= 1.0, f"refine_spread must be within [0, 1], got {self.refine_spread}")
        require(self.first_segment_samples <= self.segment_samples,
                f"first_segment_samples ({self.first_segment_samples}) must not exceed segment_samples "
                f"({self.segment_samples})")
