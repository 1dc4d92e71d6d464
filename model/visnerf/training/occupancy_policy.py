"""Which cells a training run samples: the carved hull, then occupancy grids rebuilt from the density."""


import numpy as np
import torch
from torch import Tensor

from visnerf.rendering.occupancy import (
    build_occupancy,
    cell_centres,
    dilate,
    occupied_bounds,
    query_occupancy,
)
from visnerf.training.schedule import resolution_for_box


class OccupancyPolicy:
    """The trainer's occupancy grids (a part of ``Trainer``)."""

    def _occupancy_resolution(self) -> tuple[int, int, int]:
        return tuple(min(r, self.cfg.occupancy_resolution) for r in self.field.resolution)  # type: ignore[return-value]

    def _carved_on(self, res: tuple[int, int, int]) -> Tensor:
        """The carved grid resampled (nearest cell) onto the field's box at ``res``."""
        assert self.carved is not None
        grid, box = self.carved
        centres = cell_centres(self.field.aabb.cpu(), res).reshape(-1, 3)
        return query_occupancy(grid, box, centres).reshape(res).to(self.device)

    @torch.no_grad()
    def density_occupancy(self, res: tuple[int, int, int], within: Tensor | None = None, dilation: int = 1) -> Tensor:
        """Density occupancy (union over settings) dilated by ``dilation`` cells, inside the
        carved hull when there is one and evaluated only in the cells of ``within`` when given."""
        candidates = None if self.carved is None else self._carved_on(res)
        if within is not None:
            candidates = within if candidates is None else candidates & within
        return build_occupancy(self.field, res, self.settings_all, self.step_size(),
                               self.render_cfg.occupancy_threshold, candidates, dilation=dilation)

    @torch.no_grad()
    def update_occupancy(self, shrink: bool) -> None:
        res = self._occupancy_resolution()
        grid = self.density_occupancy(res)
        if not bool(grid.any()):
            return  # nothing is visible yet: skipping all space would stop training
        if shrink:
            bounds = occupied_bounds(grid, self.field.aabb)
            if bounds is not None:
                margin = 0.02 * (bounds[1] - bounds[0]).max()
                bounds = torch.stack([torch.maximum(bounds[0] - margin, self.field.aabb[0]),
                                      torch.minimum(bounds[1] + margin, self.field.aabb[1])])
                voxels = float(np.prod(self.field.resolution)) ** (1 / 3)
                self.field.resample(resolution_for_box(bounds[1] - bounds[0], voxels), bounds)
                self.sampler.set_aabb(self.field.aabb)
                res = self._occupancy_resolution()
                grid = self.density_occupancy(res)
                self._rebuild_optimizer()
        self.field.set_occupancy(grid)

    @torch.no_grad()
    def finish_occupancy(self) -> None:
        """The inference grid at the end of training: the density's occupancy now, within the
        grid training last sampled (``refine_occupancy``).

        Training evaluates density only in that grid's cells (``render_rays`` drops the rest), so
        a cell outside it has had no photometric loss since the last occupancy milestone, while
        the shared plane and line factors went on changing its density. A grid rebuilt from the
        density alone would render such cells wherever their density has since grown past the
        threshold; intersected, inference renders only cells that training kept fitting. Without
        a grid (no carve, no milestone) it is the density's.
        """
        if self.field.occupancy is None:
            self.update_occupancy(shrink=False)
            return
        self.refine_occupancy(grow=False)

    @torch.no_grad()
    def refine_occupancy(self, grow: bool = True) -> None:
        """Rebuild the grid from the density within the cells training samples now, dilated by
        ``occupancy_refine_dilation`` cells, and keep it within ``d`` cells of that grid (and of
        the carve). So with ``d > 0`` a surface that has grown into the grid's ring of empty
        cells gets a new ring: a surface pressed against the grid's edge would be cut there, and
        a level or a density could run past the images' surface at no cost while the cut hid it.
        ``grow=False`` (``finish_occupancy``) keeps the grid within itself: cells may leave, never
        join, as a cell outside it has had no photometric loss. Only the cells within reach are
        evaluated (the rebuild costs a third of a whole box's on Nyx, where ``d`` is 0)."""
        trained = self.field.occupancy
        if trained is None:
            return
        d = self.cfg.occupancy_refine_dilation
        reach = dilate(trained, d) if grow else trained
        if grow and self.carved is not None:
            reach = reach & self._carved_on(tuple(trained.shape))  # type: ignore[arg-type]
        grid = self.density_occupancy(tuple(trained.shape), within=reach, dilation=d) & reach  # type: ignore[arg-type]
        if bool(grid.any()):
            self.field.set_occupancy(grid)
