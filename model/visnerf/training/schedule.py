"""The schedule of a training run: progress, the learning rates and the milestones it reaches.

Progress is ``max(iteration / step_limit, train_seconds / time_budget)`` (``TrainConfig.step_limit``:
under a time budget with no ``iterations`` given, the budget alone). Learning rates decay
exponentially with progress; grid upsampling, occupancy updates (the first also shrinks the box to
the content) and occupancy refinements switch on at progress fractions of the config.
"""

import math
from dataclasses import dataclass, field

import torch

from visnerf.config import TrainConfig
from visnerf.training.grid_budget import GridBudget


def resolution_for_box(extent: torch.Tensor, voxels_per_axis: int | float) -> tuple[int, int, int]:
    """Per-axis grid sizes with ``voxels_per_axis^3`` cells in all, cells as cubic as the box allows."""
    volume = float(torch.prod(extent))
    size = (volume / voxels_per_axis**3) ** (1.0 / 3.0)
    return tuple(max(2, int(round(float(e) / size))) for e in extent)  # type: ignore[return-value]


def upsample_resolutions(cfg: TrainConfig, final: float | None = None) -> list[float]:
    """Voxels per axis after each upsampling milestone, log-spaced from initial to final (``final``,
    else ``cfg.resolution_final``)."""
    n = len(cfg.upsample_at)
    lo, hi = math.log(cfg.resolution_init), math.log(cfg.resolution_final if final is None else final)
    return [math.exp(lo + (hi - lo) * (i + 1) / n) for i in range(n)]


@dataclass
class TrainState:
    """Where a run stands in its schedule (saved in the run state, partly in the checkpoint)."""

    iteration: int = 0
    train_seconds: float = 0.0
    upsamples_done: int = 0
    occupancy_done: int = 0
    refines_done: int = 0
    log: list[dict] = field(default_factory=list)
    states_written: int = 0
    """Run states written (``run_state.py``), periodic and on stop."""
    state_seconds: float = 0.0
    """Seconds spent writing them (part of ``train_seconds``)."""
    final_grid: float = 0.0
    """Voxels a side the time budget allows at the end (``TrainConfig.rays_per_voxel``, decided
    at each upsampling; 0: not decided, ``resolution_final``)."""
    mark_iteration: int = 0
    mark_seconds: float = 0.0
    """Iteration and training seconds at the last upsampling (or the start): the rays a second at
    the grid held since are measured from there."""


class Schedule:
    """The trainer's schedule (a part of ``Trainer``)."""

    def progress(self) -> float:
        limit = self.cfg.step_limit
        p = 0.0 if limit is None else self.state.iteration / limit
        if self.cfg.time_budget_s:
            p = max(p, self.state.train_seconds / self.cfg.time_budget_s)
        return p

    def lr_scale(self) -> float:
        """Factor on the base learning rates now: ``lr_decay_ratio`` to the progress made."""
        return self.cfg.lr_decay_ratio ** min(1.0, self.progress())

    def step_size(self) -> float:
        return self.field.voxel_size() * self.render_cfg.step_ratio

    def _budget_final_grid(self, now: float) -> None:
        """Decide ``state.final_grid`` from the rays a second measured since the last upsampling
        (``training.grid_budget``), within the configured final grid, and say so in the recipe's
        record of the grid."""
        steps = self.state.iteration - self.state.mark_iteration
        seconds = self.state.train_seconds - self.state.mark_seconds
        if steps <= 0 or not seconds > 0:
            return
        assert self.cfg.time_budget_s is not None
        budget = GridBudget(float(self.state.iteration * self.cfg.batch_rays), steps * self.cfg.batch_rays / seconds,
                            now, self.cfg.time_budget_s - self.state.train_seconds)
        final = budget.largest_grid(self.cfg.rays_per_voxel, float(self.cfg.resolution_final))
        self.state.final_grid = final
        for choice in self.recipe_choices:
            if choice.get("name") == "rays_per_voxel":
                reason = str(choice.get("reason", "")).split(" [at the last upsampling: ")[0]
                described = budget.describe(final, self.cfg.rays_per_voxel)
                choice["reason"] = f"{reason} [at the last upsampling: {described}]"

    def _milestones(self) -> None:
        done = (self.state.upsamples_done, self.state.occupancy_done, self.state.refines_done)
        self._schedule_milestones()
        if (self.state.upsamples_done, self.state.occupancy_done, self.state.refines_done) != done:
            self.ranks.broadcast_field(self.field)  # the ranks' grids stay identical
            self.sampler.set_aabb(self.field.aabb)

    def _schedule_milestones(self) -> None:
        p = self.progress()
        at = self.cfg.upsample_at
        while self.state.upsamples_done < len(at) and p >= at[self.state.upsamples_done]:
            now = math.prod(self.field.resolution) ** (1.0 / 3.0)
            if self.cfg.rays_per_voxel > 0 and self.cfg.time_budget_s is not None:
                self._budget_final_grid(now)
            targets = upsample_resolutions(self.cfg, self.state.final_grid or None)
            voxels = max(targets[self.state.upsamples_done], now)  # the budget never shrinks a grid
            resolution = resolution_for_box(self.field.aabb[1] - self.field.aabb[0], voxels)
            if resolution != tuple(self.field.resolution):
                self.field.resample(resolution)
            self.state.upsamples_done += 1
            self.state.mark_iteration, self.state.mark_seconds = self.state.iteration, self.state.train_seconds
            self._rebuild_optimizer()
            if self.field.occupancy is None and self.carved is not None:
                self.field.set_occupancy(self._carved_on(self._occupancy_resolution()))
        while (self.state.occupancy_done < len(self.cfg.occupancy_at)
               and p >= self.cfg.occupancy_at[self.state.occupancy_done]
               and self.state.iteration >= self.cfg.occupancy_min_iterations):
            # The carve bounds the box from the images, which cannot lose content; bounds from a
            # young density field can (seen: a time-budgeted run slowed by other jobs shrank the box
            # to a slab before the surfaces had formed and never recovered), so with a carve the
            # box is not shrunk again.
            self.update_occupancy(shrink=self.state.occupancy_done == 0 and self.carved is None)
            self.state.occupancy_done += 1
        while (self.state.occupancy_done == len(self.cfg.occupancy_at)
               and self.state.refines_done < len(self.cfg.occupancy_refine_at)
               and p >= self.cfg.occupancy_refine_at[self.state.refines_done]):
            self.refine_occupancy()
            self.state.refines_done += 1
