"""The training loop: the paper's recipe, scheduled by progress (iterations or wall time).

Progress is ``max(iteration / step_limit, train_seconds / time_budget)`` (``TrainConfig.step_limit``:
under a time budget with no ``iterations`` given, the budget alone). Learning rates decay
exponentially with progress; grid upsampling, occupancy updates (the first also shrinks the box to
the content) and occupancy refinements switch on at progress fractions of the config. Milestones
count as training time (a wall-clock budget includes them); validation does not.
"""

import csv
import json
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor
from tqdm import tqdm

from visnerf import compiled
from visnerf.checkpoint import CheckpointMeta, save_checkpoint
from visnerf.config import FieldConfig, RenderConfig, TrainConfig
from visnerf.data.carving import carve_occupancy
from visnerf.data.scene import SceneData, estimate_bbox
from visnerf.evaluation.metrics import mse_to_psnr, psnr, ssim
from visnerf.evaluation.spacing import choose_full_spacing
from visnerf.rendering.colour_sampling import ColourSampling
from visnerf.rendering.density_gradients import DensityGradientSampling
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.occupancy import (
    build_occupancy,
    cell_centres,
    dilate,
    occupied_bounds,
    parameter_settings,
    query_occupancy,
)
from visnerf.rendering.renderer import (
    RenderSettings,
    drop_occluded,
    empty_space_of,
    place_samples,
    ray_windows,
    render_image,
    shade_rays,
)
from visnerf.representation.field import VisNerfField
from visnerf.representation.vm_taps import table_gradients_in_place
from visnerf.runtime import bf16_native, keep_freed_blocks, release_free_memory
from visnerf.training.distributed import Ranks
from visnerf.training.fused_step import FusedStep, Sampling, StepBatch
from visnerf.training.ray_batches import RayBatchSampler, micro_batches, silhouette_pixels
from visnerf.training.regularizers import RegularizerWeights, backward_regularization, level_curvature, level_spacing
from visnerf.training.run_state import (
    RunStateError,
    pack_optimizer,
    read_run_state,
    scene_fingerprint,
    unpack_optimizer,
    write_run_state,
)
from visnerf.training.sparse_adam import RowSparseAdam
from visnerf.training.stop_signals import StopRequest
from visnerf.training.weight_average import WeightAverage


def resolution_for_box(extent: torch.Tensor, voxels_per_axis: int | float) -> tuple[int, int, int]:
    """Per-axis grid sizes with ``voxels_per_axis^3`` cells in all, cells as cubic as the box allows."""
    volume = float(torch.prod(extent))
    size = (volume / voxels_per_axis**3) ** (1.0 / 3.0)
    return tuple(max(2, int(round(float(e) / size))) for e in extent)  # type: ignore[return-value]


def upsample_resolutions(cfg: TrainConfig) -> list[float]:
    """Voxels per axis after each upsampling milestone, log-spaced from initial to final."""
    n = len(cfg.upsample_at)
    lo, hi = math.log(cfg.resolution_init), math.log(cfg.resolution_final)
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


FUSED_ADAM_DEVICES = ("cpu", "cuda")
"""Devices whose parameters get torch's fused Adam on the torch path: one pass over each tensor
instead of about ten elementwise kernels, the same update to 1e-6 (docs/decisions.md, "Training step")."""


def make_optimizer(field_: VisNerfField, cfg: TrainConfig, scale: float,
                   row_sparse: bool = False) -> torch.optim.Optimizer:
    """Adam over the factors and the networks (two learning rates); ``row_sparse``: the fused
    step's ``RowSparseAdam``, which updates the VM tables at the rows a step touched."""
    factors = [*field_.density_grid.parameters(), *field_.appearance_grid.parameters(),
               *field_.density_params.parameters(), *field_.appearance_params.parameters()]
    if field_.levels is not None:
        factors += list(field_.levels.parameters())
    networks = [*field_.density_decoder.parameters(), *field_.color_decoder.parameters()]
    if field_.facing is not None:
        networks += list(field_.facing.parameters())
    groups = [{"params": factors, "lr": cfg.lr_factors * scale, "base_lr": cfg.lr_factors},
              {"params": networks, "lr": cfg.lr_networks * scale, "base_lr": cfg.lr_networks}]
    if row_sparse:
        return RowSparseAdam(groups, betas=cfg.betas)
    return torch.optim.Adam(groups, betas=cfg.betas, fused=field_.device.type in FUSED_ADAM_DEVICES)


def fused_step_serves(field_: VisNerfField) -> bool:
    """Whether the fused step (``training.fused_step``) trains ``field_``: float32 on the CPU,
    where the compiled loops run."""
    return compiled.serves(field_.device) and field_.density_grid.plane_table.dtype == torch.float32


@torch.no_grad()
def validate(
    field_: VisNerfField, scene: SceneData, render_cfg: RenderConfig, max_images: int
) -> dict[str, float]:
    """Mean PSNR / SSIM over up to ``max_images`` evenly chosen frames of ``scene``."""
    idx = np.linspace(0, scene.n_frames - 1, min(max_images, scene.n_frames)).round().astype(int)
    settings = RenderSettings.from_config(render_cfg, scene.background)
    params = scene.normalized_params()
    psnrs, ssims, ms = [], [], []
    field_.eval()
    for i in np.unique(idx):
        t0 = time.perf_counter()
        with torch.inference_mode():
            img = render_image(field_, scene.c2w[i].to(field_.device), scene.intrinsics,
                               params[i].to(field_.device), settings)
        ms.append(1000 * (time.perf_counter() - t0))
        pred = img.clamp(0, 1).cpu().numpy()
        gt = scene.images[i].numpy().astype(np.float32) / 255.0
        psnrs.append(psnr(pred, gt))
        ssims.append(ssim(pred, gt))
    field_.train()
    return {"val_psnr": float(np.mean(psnrs)), "val_ssim": float(np.mean(ssims)), "val_ms_per_frame": float(np.median(ms))}


class Trainer:
    """Owns the field, the optimizer, the schedule and the log."""

    def __init__(
        self,
        train_scene: SceneData,
        val_scene: SceneData | None,
        cfg: TrainConfig,
        device: torch.device,
        field_cfg: FieldConfig | None = None,
        render_cfg: RenderConfig | None = None,
        init_field: VisNerfField | None = None,
        start: TrainState | None = None,
        carved: tuple[Tensor, Tensor] | None = None,
        setup_seconds: float = 0.0,
        fused: bool | None = None,
    ) -> None:
        """``carved``: the scene's carved grid and the box it covers, where the caller has carved
        already (``training.recipe``); otherwise the trainer carves when ``cfg.carve``.
        ``setup_seconds``: the caller's time spent on the data before (counted as training).
        ``fused``: take the fused step (None: where ``fused_step_serves``; False: the torch path,
        which every device has)."""
        self.scene, self.val_scene, self.cfg, self.device = train_scene, val_scene, cfg, device
        self.render_cfg = render_cfg or RenderConfig()
        self.spacing_note: str | None = None
        """How the full-quality spacing was chosen (None: not chosen, the configured one)."""
        if device.type == "cpu":
            keep_freed_blocks()  # table-sized tensors every step: no page faults for each (runtime.py)
        torch.manual_seed(cfg.seed)
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.setup_seconds = setup_seconds
        self.recipe_choices: list[dict] = []
        """The settings chosen from the data and why (``training.recipe``), saved in the checkpoint."""
        self.dataset_notes: list[str] = []
        """How the reader took the dataset's columns (``ParsedSplit.notes``), saved in the checkpoint."""
        self.carved: tuple[Tensor, Tensor] | None = None  # (grid, its world box)
        if init_field is None:
            aabb = estimate_bbox(train_scene) if carved is None else carved[1].clone()
            if cfg.carve:
                t0 = time.perf_counter()
                if carved is not None:
                    grid = carved[0]
                else:
                    grid = carve_occupancy(train_scene, aabb, (cfg.carve_resolution,) * 3, cfg.carve_tolerance,
                                           min_seen_fraction=cfg.carve_min_seen_fraction)
                self.setup_seconds += time.perf_counter() - t0
                bounds = occupied_bounds(grid, aabb)
                if bounds is not None:
                    self.carved = (dilate(grid, cfg.carve_dilation), aabb.clone())
                    aabb = bounds
            base = field_cfg or FieldConfig()
            resolution = resolution_for_box(aabb[1] - aabb[0], cfg.resolution_init)
            fcfg = FieldConfig(**{**base.to_dict(), "resolution": resolution,
                                  "param_lengths": tuple(len(a.values) for a in train_scene.param_axes)})
            init_field = VisNerfField(fcfg, aabb)
            init_field.set_param_knots(train_scene.knots())
        self.field = init_field.to(device).train()
        set_mixed_precision(self.field, cfg.mixed_precision)
        if self.carved is not None:
            self.field.set_occupancy(self._carved_on(self._occupancy_resolution()))
        self.state = start or TrainState(train_seconds=self.setup_seconds)  # carving counts as training
        self.sampler = RayBatchSampler(train_scene, device, self.generator)
        self.sampler.set_aabb(self.field.aabb)
        if cfg.silhouette_ray_fraction > 0.0:
            band = silhouette_pixels(train_scene.images, train_scene.background, cfg.carve_tolerance)
            self.sampler.set_silhouette_band(band, cfg.silhouette_ray_fraction)
        self.fused: FusedStep | None = None
        """The fused step where it serves (``fused_step_serves``; ``fused=False`` takes the torch path)."""
        self._use_fused = fused_step_serves(self.field) if fused is None else fused
        self._new_optimizer(1.0)
        self.settings_all = parameter_settings(train_scene.knots(), cfg.occupancy_max_settings, self.generator)
        self.weight_average: WeightAverage | None = None
        self.ema_mse: float | None = None
        """Moving average of the batches' squared error (the progress bar's PSNR)."""
        self.stopped = False
        """Whether the last ``run`` returned early on a stop request (its run state is written)."""
        self.ranks = Ranks.solo(device)
        """The processes training this field together (``distribute``); one by default."""

    def distribute(self, ranks: Ranks) -> None:
        """Train as one of ``ranks`` (``training.distributed``): from rank 0's field, drawing this
        rank's share of each batch from its own random stream. Only rank 0 validates (the others
        drop their validation frames) and finishes the run after the loop. One process: nothing
        changes (its random stream goes on as it was, as a resumed run needs)."""
        self.ranks = ranks
        if ranks.world_size == 1:
            return
        ranks.broadcast_field(self.field)
        self.sampler.set_aabb(self.field.aabb)
        self.generator.manual_seed(ranks.stream_seed(self.cfg.seed, self.state.iteration))
        if not ranks.is_main:
            self.val_scene = None

    def progress(self) -> float:
        limit = self.cfg.step_limit
        p = 0.0 if limit is None else self.state.iteration / limit
        if self.cfg.time_budget_s:
            p = max(p, self.state.train_seconds / self.cfg.time_budget_s)
        return p

    def lr_scale(self) -> float:
        """Factor on the base learning rates now: ``lr_decay_ratio`` to the progress made."""
        return self.cfg.lr_decay_ratio ** min(1.0, self.progress())

    def _rebuild_optimizer(self) -> None:
        self._new_optimizer(self.lr_scale())

    def _new_optimizer(self, scale: float) -> None:
        """A new optimizer over the field's parameters (and, on the fused path, their row marks)."""
        self.optimizer = make_optimizer(self.field, self.cfg, scale, row_sparse=self._use_fused)
        if self._use_fused:
            self.fused = FusedStep(self.field, self.optimizer)  # type: ignore[arg-type]

    def step_size(self) -> float:
        return self.field.voxel_size() * self.render_cfg.step_ratio

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

    def _milestones(self) -> None:
        done = (self.state.upsamples_done, self.state.occupancy_done, self.state.refines_done)
        self._schedule_milestones()
        if (self.state.upsamples_done, self.state.occupancy_done, self.state.refines_done) != done:
            self.ranks.broadcast_field(self.field)  # the ranks' grids stay identical
            self.sampler.set_aabb(self.field.aabb)

    def _schedule_milestones(self) -> None:
        p = self.progress()
        targets = upsample_resolutions(self.cfg)
        while self.state.upsamples_done < len(self.cfg.upsample_at) and p >= self.cfg.upsample_at[self.state.upsamples_done]:
            voxels = targets[self.state.upsamples_done]
            self.field.resample(resolution_for_box(self.field.aabb[1] - self.field.aabb[0], voxels))
            self.state.upsamples_done += 1
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

    def _weights(self) -> RegularizerWeights:
        l1 = self.cfg.l1_weight_initial if self.state.iteration < self.cfg.l1_switch_iteration else self.cfg.l1_weight_rest
        return RegularizerWeights(l1, self.cfg.param_l1_weight, self.cfg.tv_weight_density,
                                  self.cfg.tv_weight_appearance, self.cfg.tv_weight_params)

    def train_step(self) -> dict[str, float]:
        """One optimizer step over ``batch_rays`` rays, rendered and back-propagated in chunks.

        The photometric loss is a mean over the whole batch, so each chunk's squared error is
        divided by the batch size and its gradient accumulated: the step is the same as one pass
        over the batch, with activation memory bounded by ``micro_batch_rays`` rays and
        ``micro_batch_samples`` evaluated samples per chunk (``ray_batches.micro_batches``). On the
        CPU the fused path renders and back-propagates (``training.fused_step``), elsewhere the
        torch path (``_render_backward``); both take the same samples and draws.
        """
        scale = self.lr_scale()
        for group in self.optimizer.param_groups:
            group["lr"] = group["base_lr"] * scale
        self.optimizer.zero_grad(set_to_none=True)
        batch = self._step_batch()
        sampling = self._sampling(batch)
        if self.fused is not None:
            sq_error, n_samples = self.fused.render_backward(batch, sampling, self.generator, self.state.iteration)
            terms = self._level_priors(batch.params)  # first: the grid priors then see every touched row
            merge = self.ranks.merge_row_marks if self.ranks.world_size > 1 else None
            terms.update(self.fused.priors(self._weights(), merge))
        else:
            sq_error, n_samples = self._render_backward(batch, sampling)
            terms = backward_regularization(self.field, self._weights())
            terms.update(self._level_priors(batch.params))
        reg_value = sum(terms.values())
        if not math.isfinite(reg_value):  # before the step: the factors stay as they were
            raise FloatingPointError(f"non-finite regularization at iteration {self.state.iteration}")
        (sq_error,) = self.ranks.average_gradients(self.field.parameters(), sq_error)
        self.optimizer.step()
        if self.fused is not None:
            terms.update(self.fused.after_step())
            reg_value = sum(terms.values())
        stats = {"mse": sq_error, "loss": sq_error + reg_value, "samples": float(n_samples)}
        for name in ("level_curvature", "level_spacing"):
            if name in terms:
                stats[name] = terms[name]
        return stats

    def _step_batch(self) -> StepBatch:
        """This step's rays (this rank's share of the batch), targets and backgrounds."""
        cfg = self.cfg
        rays, n = self.ranks.batch_share(cfg.batch_rays)  # one process: all of them, their count
        batch = self.sampler.sample(rays)
        if cfg.random_background:
            bg = torch.rand(batch.rgb.shape, generator=self.generator).to(self.device)
        else:
            bg = torch.tensor(self.scene.background, device=self.device).expand_as(batch.rgb)
        target = batch.rgb
        if cfg.random_background:
            # Target pixels of background colour stand for empty space: re-composite them on bg.
            is_bg = (batch.rgb - torch.tensor(self.scene.background, device=self.device)).abs().amax(-1) < 1e-3
            target = torch.where(is_bg[:, None], bg, batch.rgb)
        return StepBatch(batch.rays_o, batch.rays_d, batch.params, target, bg, n)

    def _sampling(self, batch: StepBatch) -> Sampling:
        """Where this step samples its rays (each only its occupied span) and how it shades them."""
        cfg = self.cfg
        step = self.step_size()
        empty = empty_space_of(self.field)
        if empty is not None and step > empty.min_cell_size():
            empty = None  # a grid finer than the step: the windows would not hold every jittered sample
        windows = None if empty is None else occupied_windows(self.field, batch.rays_o, batch.rays_d, step, empty)
        density_grads = None
        if cfg.density_grad_keep < 1.0:
            density_grads = DensityGradientSampling(cfg.density_grad_floor, cfg.density_grad_keep, self.generator)
        colour_sampling = None
        if cfg.colour_weight_floor > 0.0:
            colour_sampling = ColourSampling(cfg.colour_weight_floor, self.generator)
        return Sampling(step, self.render_cfg.max_samples, self.field.occupancy, windows, cfg.stop_eps,
                        self.render_cfg.weight_threshold, density_grads, colour_sampling, cfg.micro_batch_rays,
                        cfg.micro_batch_samples)

    def _render_backward(self, batch: StepBatch, sampling: Sampling) -> tuple[float, int]:
        """The torch path of ``FusedStep.render_backward`` (every device)."""
        samples = place_samples(self.field, batch.rays_o, batch.rays_d, sampling.step, sampling.max_samples,
                                sampling.occupancy, self.generator, sampling.windows)
        samples = drop_occluded(self.field, samples, batch.params, sampling.stop_eps)
        per_ray = samples.per_ray()
        sq_error = 0.0
        for sl in micro_batches(per_ray, sampling.micro_batch_rays, sampling.micro_batch_samples):
            out = shade_rays(self.field, batch.rays_d[sl], batch.params[sl], batch.background[sl], samples.of_rays(sl),
                             sampling.weight_threshold, sampling.density_grads, sampling.colour_sampling)
            part = ((out["rgb"] - batch.target[sl]) ** 2).mean(-1).sum() / batch.divisor  # this chunk's share
            if not torch.isfinite(part):
                raise FloatingPointError(f"non-finite loss at iteration {self.state.iteration}")
            if part.requires_grad:  # a chunk whose rays meet no occupied cell has nothing to learn
                with table_gradients_in_place():  # each chunk's factor gradients add into .grad
                    part.backward()
            sq_error += float(part.detach())
        return sq_error, int(per_ray.sum())

    def _level_priors(self, params: Tensor) -> dict[str, float]:
        """A level axis's curvature and spacing priors, back-propagated; their values."""
        cfg, terms = self.cfg, {}
        if self.field.levels is None:
            return terms
        if cfg.level_curvature_weight > 0:
            # at the parameter values of random rays of the batch (the other axes' density features)
            pick = torch.randint(0, params.shape[0], (cfg.level_curvature_points,), generator=self.generator)
            raw = None if self.fused is None else self.fused.raw_density
            curvature = cfg.level_curvature_weight * level_curvature(self.field, params[pick.to(self.device)],
                                                                     self.generator, raw_density=raw)
            curvature.backward()
            terms["level_curvature"] = float(curvature.detach())
        if cfg.level_spacing_weight > 0:
            spacing = cfg.level_spacing_weight * level_spacing(self.field, cfg.level_spacing_ratio)
            if spacing.requires_grad:  # fewer than three levels: no neighbouring bands to hold
                spacing.backward()
                terms["level_spacing"] = float(spacing.detach())
        return terms

    def run(
        self,
        progress_bar: bool = True,
        on_validate: Callable[[dict[str, float]], None] | None = None,
        state_path: Path | None = None,
        stop: StopRequest | None = None,
    ) -> list[dict]:
        """Train until the iteration count or the time budget is reached; returns the log.

        With ``state_path`` the run state (``run_state.py``) is written there every
        ``checkpoint_every_s`` seconds of training and when the loop ends. With ``stop``, a stop
        request ends the loop before the next step: the state is written (with ``state_path``),
        ``stopped`` is set and the log returned without the final steps (weight average,
        occupancy, spacing), which a resumed run does.
        """
        cfg = self.cfg
        wall0 = time.perf_counter()
        last_val = last_state = self.state.train_seconds
        self.stopped = False
        # Under a time budget the bar counts seconds of training (its rate and time left are then
        # those of the budget, not of an iteration count the run never reaches).
        timed = cfg.time_budget_s is not None
        bar = tqdm(total=round(cfg.time_budget_s) if timed else cfg.step_limit,
                   initial=min(round(self.state.train_seconds), round(cfg.time_budget_s)) if timed else self.state.iteration,
                   unit="s" if timed else "it", disable=not progress_bar, dynamic_ncols=True, desc="train")
        while self._go_on(stop):
            t0 = time.perf_counter()  # milestones (upsampling, occupancy grids) are training time
            self._milestones()
            stats = self.train_step()
            self.state.iteration += 1
            self._average_weights()
            dt = time.perf_counter() - t0
            self.state.train_seconds += dt
            if self.state.iteration % self.cfg.trim_every == 0:
                release_free_memory()
            self.ema_mse = stats["mse"] if self.ema_mse is None else 0.95 * self.ema_mse + 0.05 * stats["mse"]
            if timed:
                bar.update(max(0, min(round(self.state.train_seconds), bar.total) - bar.n))
            else:
                bar.update(1)
            if self.state.iteration % 10 == 0:
                bar.set_postfix(it=self.state.iteration, loss=f"{stats['loss']:.4f}",
                                psnr=f"{mse_to_psnr(self.ema_mse):.2f}", res=str(self.field.resolution[0]), refresh=False)
            if self.val_scene is not None and self.state.train_seconds - last_val >= cfg.validate_every_s:
                last_val = self.state.train_seconds
                self._record(mse_to_psnr(self.ema_mse), wall0, on_validate)
            if (state_path is not None and cfg.checkpoint_every_s > 0
                    and self.state.train_seconds - last_state >= cfg.checkpoint_every_s):
                self.write_run_state(state_path)
                last_state = self.state.train_seconds
        bar.close()
        if state_path is not None and (self.stopped or cfg.checkpoint_every_s > 0):
            self.write_run_state(state_path)  # a stop during the final steps resumes from here
        if self.stopped or not self.ranks.is_main:
            return self.state.log
        if stop is not None:
            stop.loop_ended()
        compared = self._use_weight_average()
        self.finish_occupancy()  # final grid, for fast inference
        if cfg.choose_full_spacing:
            # Without held-out frames the training frames serve: the choice weighs each spacing's
            # sampling error against the exhaustive render of the same frame, not how the model
            # generalises, which costs nothing measurable (docs/decisions.md, "Rendering").
            held_out = self.val_scene is not None
            frames = self.val_scene if held_out else self.scene
            choice = choose_full_spacing(self.field, frames, self.render_cfg, cfg.validate_max_images)
            self.render_cfg = replace(self.render_cfg, full_step_ratio=choice.ratio)
            self.spacing_note = choice.describe(training_frames=not held_out)
            if progress_bar:
                tqdm.write(self.spacing_note)
        self._record(mse_to_psnr(self.ema_mse) if self.ema_mse else float("nan"), wall0, on_validate, compared)
        return self.state.log

    def _go_on(self, stop: StopRequest | None) -> bool:
        """Whether to take another step: progress is left and no stop was asked for (which sets
        ``stopped``). Ranks agree on both: rank 0's training clock, any rank's stop request."""
        asked = stop is not None and stop.requested()
        self.state.train_seconds, asked = self.ranks.agree(self.state.train_seconds, asked)
        if self.progress() >= 1.0:
            return False
        self.stopped = asked
        return not asked

    def write_run_state(self, path: Path) -> Path:
        """Write everything this run needs to go on (``run_state.py``); the time it takes counts
        as training time (``TrainState.state_seconds``)."""
        t0 = time.perf_counter()
        tensors, document = self.capture_run_state()
        write_run_state(path, tensors, document)
        dt = time.perf_counter() - t0
        self.state.states_written += 1
        self.state.state_seconds += dt
        self.state.train_seconds += dt
        return path

    def capture_run_state(self) -> tuple[dict[str, Tensor], dict[str, Any]]:
        """(tensors, JSON document) of the run as it stands between two steps."""
        tensors = {f"field.{name}": value.float() if value.is_floating_point() else value
                   for name, value in self.field.state_dict().items() if name != "occupancy"}
        if self.field.occupancy is not None:
            tensors["occupancy"] = self.field.occupancy.to(torch.uint8)
        optimizer_tensors, optimizer_doc = pack_optimizer(self.optimizer)
        tensors.update(optimizer_tensors)
        average = None
        if self.weight_average is not None and self.weight_average.follows(self.field):
            tensors.update({f"average.{i}": a for i, a in enumerate(self.weight_average.average)})
            average = {"span": self.weight_average.span, "progress": self.weight_average.progress}
        tensors["rng.torch"] = torch.get_rng_state()
        tensors["rng.generator"] = self.generator.get_state()
        if self.device.type == "cuda":
            tensors["rng.cuda"] = torch.cuda.get_rng_state(self.device)
        if self.carved is not None:
            tensors["carved.grid"], tensors["carved.box"] = self.carved[0].to(torch.uint8), self.carved[1]
        tensors["settings"] = self.settings_all
        document = {
            "scene": scene_fingerprint(self.scene),
            "state": asdict(self.state),
            "train": self.cfg.to_dict(),
            "field": self.field.current_config().to_dict(),
            "render": self.render_cfg.to_dict(),
            "choices": self.recipe_choices,
            "dataset_notes": self.dataset_notes,
            "setup_seconds": self.setup_seconds,
            "ema_mse": self.ema_mse,
            "optimizer": optimizer_doc,
            "weight_average": average,
        }
        return tensors, document

    @classmethod
    def from_run_state(
        cls,
        path: Path,
        train_scene: SceneData,
        val_scene: SceneData | None,
        device: torch.device,
        train_overrides: dict[str, Any] | None = None,
        render_overrides: dict[str, Any] | None = None,
    ) -> "Trainer":
        """The run saved at ``path``, ready to go on where it stopped: the same field, optimizer
        moments, weight average, random state, occupancy and schedule position. The training
        configuration is the run's, with ``train_overrides`` (a longer budget, say) on top.
        ``RunStateError`` if the file is unusable or was written for other training frames."""
        document, tensors = read_run_state(path)
        if document["scene"] != scene_fingerprint(train_scene):
            raise RunStateError(f"{path} was written for other training frames (another dataset, split or "
                                "hold-out); resume with the data and hold-out options of the run that wrote it")
        try:
            cfg = TrainConfig.from_dict({**document["train"], **(train_overrides or {})})
            render_cfg = RenderConfig.from_dict({**document["render"], **(render_overrides or {})})
            field_cfg = FieldConfig.from_dict(document["field"])
            start = TrainState(**document["state"])
        except (KeyError, TypeError, ValueError) as exc:
            raise RunStateError(f"{path}: the run's configuration cannot be read back: {exc}") from None
        field_ = VisNerfField(field_cfg, tensors["field.aabb"])
        try:
            field_.load_state_dict({name[len("field."):]: value for name, value in tensors.items()
                                    if name.startswith("field.")}, strict=True)
        except RuntimeError as exc:
            raise RunStateError(f"{path}: the field's tensors do not match its configuration: {exc}") from None
        if "occupancy" in tensors:
            field_.set_occupancy(tensors["occupancy"].bool())
        trainer = cls(train_scene, val_scene, cfg, device, render_cfg=render_cfg, init_field=field_, start=start)
        trainer._restore(document, tensors)
        return trainer

    def _restore(self, document: dict[str, Any], tensors: dict[str, Tensor]) -> None:
        """Put back what ``capture_run_state`` saved beyond the field and the schedule."""
        unpack_optimizer(self.optimizer, tensors, document["optimizer"])
        average = document.get("weight_average")
        if average is not None:
            live = list(self.field.parameters())
            saved = [tensors[f"average.{i}"].to(self.device) for i in range(len(live))]
            self.weight_average = WeightAverage(float(average["span"]), live, saved, float(average["progress"]))
        torch.set_rng_state(tensors["rng.torch"])
        self.generator.set_state(tensors["rng.generator"])
        if "rng.cuda" in tensors and self.device.type == "cuda":
            torch.cuda.set_rng_state(tensors["rng.cuda"], self.device)
        if "carved.grid" in tensors:
            self.carved = (tensors["carved.grid"].bool(), tensors["carved.box"].float())
        self.settings_all = tensors["settings"]
        self.recipe_choices = list(document.get("choices", []))
        self.dataset_notes = list(document.get("dataset_notes", []))
        self.setup_seconds = float(document.get("setup_seconds", 0.0))
        self.ema_mse = document.get("ema_mse")

    def _average_weights(self) -> None:
        """Keep the parameters' moving average from ``weight_average_from`` on, every
        ``weight_average_every`` steps; (re)start it where it does not follow the field's current
        parameters (none yet, or the grid was upsampled since)."""
        cfg = self.cfg
        p = self.progress()
        if cfg.weight_average_span <= 0.0 or p < cfg.weight_average_from:
            return
        if self.weight_average is None or not self.weight_average.follows(self.field):
            self.weight_average = WeightAverage.start(self.field, cfg.weight_average_span, p)
        elif self.state.iteration % cfg.weight_average_every == 0:
            self.weight_average.update(p)

    def _use_weight_average(self) -> dict[str, float]:
        """At the end of training, replace the parameters by their moving average (if one is kept).
        With validation frames, returns the last live parameters' and the average's validation
        PSNR on them, both rendered the same way just before and after the swap (before the final
        occupancy grid and spacing), so that a run's log compares the two."""
        average = self.weight_average
        if average is None or not average.follows(self.field):
            return {}
        average.update(self.progress())
        compared = {}
        if self.val_scene is not None:
            compared["live_val_psnr"] = validate(self.field, self.val_scene, self.render_cfg,
                                                 self.cfg.validate_max_images)["val_psnr"]
        try:
            average.copy_into(self.field)
        except FloatingPointError as exc:  # the run's result stays: the last parameters, unchanged
            warnings.warn(f"{exc}; the checkpoint holds the last parameters", RuntimeWarning, stacklevel=2)
            return compared
        if self.val_scene is not None:
            compared["average_val_psnr"] = validate(self.field, self.val_scene, self.render_cfg,
                                                    self.cfg.validate_max_images)["val_psnr"]
        return compared

    def _record(self, train_psnr: float, wall0: float, on_validate: Callable | None,
                extra: dict[str, float] | None = None) -> None:
        row = {"iteration": self.state.iteration, "train_seconds": round(self.state.train_seconds, 2),
               "wall_seconds": round(time.perf_counter() - wall0, 2), "train_psnr": round(train_psnr, 3),
               "resolution": self.field.resolution[0]}
        if self.field.occupancy is not None:
            row["occupied_cells"] = int(self.field.occupancy.sum())
        if self.val_scene is not None:
            row.update({k: round(v, 4) for k, v in validate(self.field, self.val_scene, self.render_cfg,
                                                              self.cfg.validate_max_images).items()})
        row.update({k: round(v, 4) for k, v in (extra or {}).items()})
        self.state.log.append(row)
        if on_validate is not None:
            on_validate(row)

    def save(self, path: str | Path, dataset: str = "") -> Path:
        """Checkpoint plus the training log (``<stem>.log.csv`` and ``.json``) beside it."""
        path = Path(path)
        s = self.scene
        last = self.state.log[-1] if self.state.log else {}
        meta = CheckpointMeta(
            field=self.field.current_config(),
            render=self.render_cfg,
            param_axes=s.param_axes,
            bbox=tuple(tuple(float(x) for x in c) for c in self.field.aabb.cpu()),  # type: ignore[arg-type]
            background=s.background,
            camera=s.default_camera(),
            image_width=s.intrinsics.width,
            image_height=s.intrinsics.height,
            title=s.title,
            kind=s.kind,
            provenance={"dataset": dataset or s.source, "iterations": self.state.iteration,
                        "train_seconds": round(self.state.train_seconds, 1),
                        "val_psnr": last.get("val_psnr"), "val_ssim": last.get("val_ssim"),
                        "seed": self.cfg.seed, "upsamples_done": self.state.upsamples_done,
                        "occupancy_done": self.state.occupancy_done,
                        "refines_done": self.state.refines_done, "full_spacing": self.spacing_note,
                        "run_states": {"written": self.state.states_written,
                                       "seconds": round(self.state.state_seconds, 2)},
                        "recipe": self.cfg.to_dict(),  # the whole TrainConfig (visnerf info shows it)
                        "choices": self.recipe_choices, "dataset_notes": self.dataset_notes,
                        **self.ranks.provenance()},
        )
        save_checkpoint(self.field, meta, path)
        write_log(self.state.log, path.with_suffix(".log.csv"))
        return path


def occupied_windows(
    field_: VisNerfField, rays_o: Float[Tensor, "n 3"], rays_d: Float[Tensor, "n 3"], step: float,
    empty_space: EmptySpace,
) -> tuple[Int[Tensor, " n"], Int[Tensor, " n"]]:
    """Each ray's first and last lattice sample (``t_near + step * (i + 0.5)``) within one cell
    of an occupied cell, ``first > last`` for a ray with none: its stratified samples in occupied
    cells lie between them (``EmptySpace.sample_window``). Needs a step no larger than a cell."""
    if step > empty_space.min_cell_size():
        raise ValueError(f"step {step} is larger than the occupancy grid's cells ({empty_space.min_cell_size()})")
    windows = ray_windows(field_, rays_o, rays_d, step, None, empty_space, near=1)
    return windows.first, windows.last


def set_mixed_precision(field_: VisNerfField, enabled: bool) -> bool:
    """Run the decoders' matrix products in bfloat16 if asked and the device does it natively."""
    use = enabled and bf16_native(field_.device)
    field_.density_decoder.bf16 = field_.color_decoder.bf16 = use
    return use



def write_log(rows: list[dict], path: Path) -> None:
    if not rows:
        return
    keys = list(dict.fromkeys(k for row in rows for k in row))
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
    path.with_suffix(".json").write_text(json.dumps(rows, indent=1))
