"""``BakeConfig``: how one parameter setting of a model is baked into a grid a browser can march
(``visnerf.bake``)."""

from dataclasses import dataclass

from visnerf.config.checks import check_types, check_whole_in, require


@dataclass(frozen=True)
class BakeConfig:
    """The bake's grid, its bricks and the fit of each vertex's view-dependent colour."""

    grid_scale: float = 1.0
    """Bake vertices per model grid vertex along each axis: 1 bakes at the model's own grid
    (docs/decisions.md#bake.grid)."""
    brick: int = 8
    """Vertices per brick and axis; only bricks that hold a vertex of an occupied cell are stored."""
    max_sh_degree: int = 1
    """Highest degree of the spherical harmonics of the view a vertex's colour is fitted with (a
    level axis's cosines come on top): the bake takes the lowest degree whose fit is within
    ``sh_tolerance`` of the model's colours on a sample of vertices (docs/decisions.md#bake.shading)."""
    sh_tolerance: float = 1.0
    """RMS colour error, in levels of 255, a degree's fit may leave on the sample."""
    sh_sample: int = 4096
    """Vertices the degree is chosen on (evenly spread over those coloured)."""
    directions_per_basis: int = 3
    """View directions the colour of a vertex is evaluated at, per basis function of its fit."""
    ridge: float = 1e-3
    """Tikhonov weight of the least-squares fit of a vertex's colour (guards flat directions)."""
    logit_clip: float = 10.0
    """The colour decoder's outputs are clipped to this before the fit: a saturated channel
    (sigmoid within 5e-5 of 0 or 1) would otherwise pull the fit away from the visible range."""
    max_vertices: int = 1 << 24
    """Largest bake grid (vertices): beyond it ``bake_setting`` refuses, naming the size."""

    def __post_init__(self) -> None:
        check_types(type(self), self.__dict__)
        check_whole_in(self, 2, 32, "brick")
        check_whole_in(self, 0, 2, "max_sh_degree")
        check_whole_in(self, 16, 1 << 20, "sh_sample")
        require(0.0 < self.sh_tolerance <= 64.0, f"sh_tolerance must be within (0, 64], got {self.sh_tolerance}")
        check_whole_in(self, 2, 16, "directions_per_basis")
        check_whole_in(self, 8, 1 << 28, "max_vertices")
        require(0.25 <= self.grid_scale <= 4.0, f"grid_scale must be within [0.25, 4], got {self.grid_scale}")
        require(0.0 < self.ridge <= 1.0, f"ridge must be within (0, 1], got {self.ridge}")
        require(1.0 <= self.logit_clip <= 30.0, f"logit_clip must be within [1, 30], got {self.logit_clip}")
