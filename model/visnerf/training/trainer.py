"""The training loop: a field, its optimizer, its schedule and its log, stepped until the run ends.

The trainer's jobs live in their own modules: the schedule and its milestones (``schedule``), the
occupancy grids (``occupancy_policy``), a step (``step``, ``fused_step``), the run state written
and read back (``resume``) and what a run records (``record``). Milestones count as training time
(a wall-clock budget includes them); validation does not.
"""

import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import torch
from torch import Tensor
from tqdm import tqdm

from visnerf.config import FieldConfig, RenderConfig, TrainConfig
from visnerf.data.carving import carve_occupancy
from visnerf.data.scene import SceneData, estimate_bbox
from visnerf.evaluation.metrics import mse_to_psnr
from visnerf.evaluation.spacing import choose_full_spacing
from visnerf.rendering.occupancy import dilate, occupied_bounds, parameter_settings
from visnerf.representation.field import VisNerfField
from visnerf.runtime import keep_freed_blocks, release_free_memory
from visnerf.training.distributed import Ranks
from visnerf.training.fused_step import FusedStep
from visnerf.training.occupancy_policy import OccupancyPolicy
from visnerf.training.ray_batches import RayBatchSampler, silhouette_pixels
from visnerf.training.record import Recording
from visnerf.training.resume import Resumable
from visnerf.training.schedule import Schedule, TrainState, resolution_for_box
from visnerf.training.step import Stepping, fused_step_serves, make_optimizer, set_mixed_precision
from visnerf.training.stop_signals import StopRequest
from visnerf.training.weight_average import WeightAverage


class Trainer(Schedule, OccupancyPolicy, Stepping, Resumable, Recording):
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
            init_field = self._initial_field(field_cfg or FieldConfig(), carved)
        self.field = init_field.to(device).train()
        set_mixed_precision(self.field, cfg.mixed_precision)
        if self.carved is not None:
            self.field.set_occupancy(self._carved_on(self._occupancy_resolution()))
        # carving counts as training
        self.state = start or TrainState(train_seconds=self.setup_seconds, mark_seconds=self.setup_seconds)
        self.sampler = self._make_sampler()
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

    def _initial_field(self, base: FieldConfig, carved: tuple[Tensor, Tensor] | None) -> VisNerfField:
        """A fresh field over the content box: the carved one where carving finds content (its grid
        kept in ``self.carved`` for the first occupancy), else the box every camera sees."""
        cfg, scene = self.cfg, self.scene
        aabb = estimate_bbox(scene) if carved is None else carved[1].clone()
        if cfg.carve:
            t0 = time.perf_counter()
            if carved is not None:
                grid = carved[0]
            else:
                grid = carve_occupancy(scene, aabb, (cfg.carve_resolution,) * 3, cfg.carve_tolerance,
                                       min_seen_fraction=cfg.carve_min_seen_fraction)
            self.setup_seconds += time.perf_counter() - t0
            bounds = occupied_bounds(grid, aabb)
            if bounds is not None:
                self.carved = (dilate(grid, cfg.carve_dilation), aabb.clone())
                aabb = bounds
        resolution = resolution_for_box(aabb[1] - aabb[0], cfg.resolution_init)
        fcfg = FieldConfig(**{**base.to_dict(), "resolution": resolution,
                              "param_lengths": tuple(len(a.values) for a in scene.param_axes)})
        field = VisNerfField(fcfg, aabb)
        field.set_param_knots(scene.knots())
        return field

    def _make_sampler(self) -> RayBatchSampler:
        """Rays of the training frames inside the field's box, a share on the silhouettes' band."""
        sampler = RayBatchSampler(self.scene, self.device, self.generator)
        sampler.set_aabb(self.field.aabb)
        if self.cfg.silhouette_ray_fraction > 0.0:
            band = silhouette_pixels(self.scene.images, self.scene.background, self.cfg.carve_tolerance)
            sampler.set_silhouette_band(band, self.cfg.silhouette_ray_fraction)
        return sampler

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


    def _rebuild_optimizer(self) -> None:
        self._new_optimizer(self.lr_scale())

    def _new_optimizer(self, scale: float) -> None:
        """A new optimizer over the field's parameters (and, on the fused path, their row marks)."""
        self.optimizer = make_optimizer(self.field, self.cfg, scale, row_sparse=self._use_fused)
        if self._use_fused:
            self.fused = FusedStep(self.field, self.optimizer)  # type: ignore[arg-type]


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
        bar = self._progress_bar(progress_bar)
        while self._go_on(stop):
            stats = self._timed_step()
            self._show_progress(bar, stats)
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
        self._finish(wall0, on_validate, progress_bar)
        return self.state.log

    def _progress_bar(self, shown: bool) -> tqdm:
        """Under a time budget the bar counts seconds of training (its rate and time left are then
        those of the budget, not of an iteration count the run never reaches)."""
        budget = self.cfg.time_budget_s
        if budget is not None:
            return tqdm(total=round(budget), initial=min(round(self.state.train_seconds), round(budget)), unit="s",
                        disable=not shown, dynamic_ncols=True, desc="train")
        return tqdm(total=self.cfg.step_limit, initial=self.state.iteration, unit="it", disable=not shown,
                    dynamic_ncols=True, desc="train")

    def _timed_step(self) -> dict[str, float]:
        """One step with its milestones (upsampling, occupancy grids), all counted as training time."""
        t0 = time.perf_counter()
        self._milestones()
        stats = self.train_step()
        self.state.iteration += 1
        self._average_weights()
        self.state.train_seconds += time.perf_counter() - t0
        if self.state.iteration % self.cfg.trim_every == 0:
            release_free_memory()
        self.ema_mse = stats["mse"] if self.ema_mse is None else 0.95 * self.ema_mse + 0.05 * stats["mse"]
        return stats

    def _show_progress(self, bar: tqdm, stats: dict[str, float]) -> None:
        if self.cfg.time_budget_s is not None:
            bar.update(max(0, min(round(self.state.train_seconds), bar.total) - bar.n))
        else:
            bar.update(1)
        if self.state.iteration % 10 == 0:
            bar.set_postfix(it=self.state.iteration, loss=f"{stats['loss']:.4f}",
                            psnr=f"{mse_to_psnr(self.ema_mse):.2f}", res=str(self.field.resolution[0]), refresh=False)

    def _finish(self, wall0: float, on_validate: Callable[[dict[str, float]], None] | None, shown: bool) -> None:
        """The final steps: the weight average where it wins, the final occupancy grid, the
        full-quality spacing, and the last record."""
        compared = self._use_weight_average()
        self.finish_occupancy()  # final grid, for fast inference
        if self.cfg.choose_full_spacing:
            # Without held-out frames the training frames serve: the choice weighs each spacing's
            # sampling error against the exhaustive render of the same frame, not how the model
            # generalises, which costs nothing measurable (docs/decisions.md#render.spacing).
            held_out = self.val_scene is not None
            frames = self.val_scene if held_out else self.scene
            choice = choose_full_spacing(self.field, frames, self.render_cfg, self.cfg.validate_max_images)
            self.render_cfg = replace(self.render_cfg, full_step_ratio=choice.ratio)
            self.spacing_note = choice.describe(training_frames=not held_out)
            if shown:
                tqdm.write(self.spacing_note)
        self._record(mse_to_psnr(self.ema_mse) if self.ema_mse else float("nan"), wall0, on_validate, compared)

    def _go_on(self, stop: StopRequest | None) -> bool:
        """Whether to take another step: progress is left and no stop was asked for (which sets
        ``stopped``). Ranks agree on both: rank 0's training clock, any rank's stop request."""
        asked = stop is not None and stop.requested()
        self.state.train_seconds, asked = self.ranks.agree(self.state.train_seconds, asked)
        if self.progress() >= 1.0:
            return False
        self.stopped = asked
        return not asked


