"""One training step: the batch, where it is sampled, the render and its backward, the priors, Adam.

On the CPU the fused path renders and back-propagates (``training.fused_step``), elsewhere the torch
path (``Stepping._render_backward``); both take the same samples and draws.
"""

import math

import torch
from jaxtyping import Float, Int
from torch import Tensor

from visnerf import compiled
from visnerf.config import TrainConfig
from visnerf.rendering.colour_sampling import ColourSampling
from visnerf.rendering.density_gradients import DensityGradientSampling
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.ray_windows import empty_space_of, ray_windows
from visnerf.rendering.training_render import drop_occluded, place_samples, shade_rays
from visnerf.representation.field import VisNerfField
from visnerf.runtime import bf16_native
from visnerf.training.fused_step import Sampling, StepBatch
from visnerf.training.ray_batches import micro_batches
from visnerf.training.regularizers import (
    LevelPriorWeights,
    RegularizerWeights,
    backward_level_priors,
    backward_regularization,
)
from visnerf.training.sparse_adam import RowSparseAdam

FUSED_ADAM_DEVICES = ("cpu", "cuda")
"""Devices whose parameters get torch's fused Adam on the torch path: one pass over each tensor
instead of about ten elementwise kernels, the same update to 1e-6 (docs/decisions.md#step.torch_fused_adam)."""


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


class Stepping:
    """The trainer's step (a part of ``Trainer``)."""

    def _weights(self) -> RegularizerWeights:
        early = self.state.iteration < self.cfg.l1_switch_iteration
        l1 = self.cfg.l1_weight_initial if early else self.cfg.l1_weight_rest
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
        bg = torch.tensor(self.scene.background, device=self.device).expand_as(batch.rgb)
        return StepBatch(batch.rays_o, batch.rays_d, batch.params, batch.rgb, bg, n)

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
        """The torch path of ``FusedStep.render_backward`` (every device). The rays' parameter
        features are computed once: the chunks back-propagate into detached copies, whose gradient
        then goes back through the parameter factors in one pass."""
        samples = place_samples(self.field, batch.rays_o, batch.rays_d, sampling.step, sampling.max_samples,
                                sampling.occupancy, self.generator, sampling.windows)
        features = self.field.param_features(batch.params)  # ([n, d], [n, c]) with their graph
        leaves = tuple(f.detach().requires_grad_(f.requires_grad) for f in features)
        samples = drop_occluded(self.field, samples, batch.params, sampling.stop_eps, q_density=leaves[0].detach())
        per_ray = samples.per_ray()
        sq_error = 0.0
        for sl in micro_batches(per_ray, sampling.micro_batch_rays, sampling.micro_batch_samples):
            out = shade_rays(self.field, batch.rays_d[sl], batch.params[sl], batch.background[sl], samples.of_rays(sl),
                             sampling.weight_threshold, sampling.density_grads, sampling.colour_sampling,
                             features=(leaves[0][sl], leaves[1][sl]))
            part = ((out["rgb"] - batch.target[sl]) ** 2).mean(-1).sum() / batch.divisor  # this chunk's share
            if not torch.isfinite(part):
                raise FloatingPointError(f"non-finite loss at iteration {self.state.iteration}")
            if part.requires_grad:  # a chunk whose rays meet no occupied cell has nothing to learn
                part.backward()
            sq_error += float(part.detach())
        reached = [(f, leaf.grad) for f, leaf in zip(features, leaves, strict=True) if leaf.grad is not None]
        if reached:
            torch.autograd.backward([f for f, _ in reached], [g for _, g in reached])
        return sq_error, int(per_ray.sum())

    def _level_priors(self, params: Tensor) -> dict[str, float]:
        """``regularizers.backward_level_priors`` with this run's weights."""
        cfg = self.cfg
        weights = LevelPriorWeights(cfg.level_curvature_weight, cfg.level_curvature_points, cfg.level_spacing_weight,
                                    cfg.level_spacing_ratio)
        raw = None if self.fused is None else self.fused.raw_density
        return backward_level_priors(self.field, params, weights, self.generator, raw)
