"""The fused training step on the CPU: compact samples, compiled lookups and compositing, row-sparse
gradients, lazy grid priors.

``Trainer.train_step`` draws the batch and steps the optimizer; between the two it calls
``FusedStep`` (the CPU with numba) or the torch path (every device). The fused path places each
ray's samples compactly (``rendering.compact_samples``), drops occluded ones
(``compact_render.drop_occluded_compact``), shades and composites them
(``compact_render.shade_compact``) and back-propagates micro-batch by micro-batch; the VM tables'
gradients land in ``RowGradients`` with the rows they touched marked, the grid priors are added
at those rows (``row_priors``) and ``RowSparseAdam`` updates them alone. Same samples, draws and
gradients as the torch path at the rows a step touches (tested in float64).
"""

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor

from visnerf.rendering.colour_sampling import ColourSampling
from visnerf.rendering.compact_render import drop_occluded_compact, shade_compact
from visnerf.rendering.compact_samples import CompactSamples, place_compact
from visnerf.rendering.density_gradients import DensityGradientSampling
from visnerf.representation.field import VisNerfField
from visnerf.representation.table_gradients import TableGradient
from visnerf.representation.training_field import TrainingField
from visnerf.training.ray_batches import micro_batches
from visnerf.training.regularizers import RegularizerWeights, backward_param_priors
from visnerf.training.row_priors import add_l1_at_marks, add_total_variation_at_marks, l1_coefficients
from visnerf.training.sparse_adam import RowSparseAdam


@dataclass(frozen=True)
class StepBatch:
    """What one step renders: rays, their targets and backgrounds, the divisor of the squared
    error (the global batch size over the ranks)."""

    rays_o: Float[Tensor, "n 3"]
    rays_d: Float[Tensor, "n 3"]
    params: Float[Tensor, "n k"]
    target: Float[Tensor, "n 3"]
    background: Float[Tensor, "n 3"]
    divisor: float


@dataclass(frozen=True)
class Sampling:
    """How a step places and shades its samples (from the configurations and the trainer's state)."""

    step: float
    max_samples: int
    occupancy: Tensor | None
    windows: tuple[Int[Tensor, " n"], Int[Tensor, " n"]] | None
    stop_eps: float
    weight_threshold: float
    density_grads: DensityGradientSampling | None
    colour_sampling: ColourSampling | None
    micro_batch_rays: int
    micro_batch_samples: int


class FusedStep:
    """The fused path of one field: its ``TrainingField``, whose VM table gradients the optimizer
    takes (``RowSparseAdam.set_row_source``)."""

    def __init__(self, field: VisNerfField, optimizer: RowSparseAdam) -> None:
        self.field = field
        self.tfield = TrainingField(field)
        for grads in self.tfield.row_gradients():
            for table in grads.tables():
                optimizer.set_row_source(table.table, table)

    def follows(self, field: VisNerfField) -> bool:
        return self.tfield.follows(field)

    def tables(self) -> list[TableGradient]:
        return [t for g in self.tfield.row_gradients() for t in g.tables()]

    def place(self, batch: StepBatch, sampling: Sampling, generator: torch.Generator) -> CompactSamples:
        samples = place_compact(self.field.aabb, batch.rays_o, batch.rays_d, sampling.step, sampling.max_samples,
                                sampling.occupancy, generator, sampling.windows)
        return drop_occluded_compact(self.tfield, samples, batch.params, sampling.step, sampling.stop_eps)

    def render_backward(self, batch: StepBatch, sampling: Sampling, generator: torch.Generator,
                        iteration: int) -> tuple[float, int]:
        """Render the batch micro-batch by micro-batch and back-propagate the photometric loss
        (the batch's mean squared error over ``divisor``); returns (its value, samples evaluated)."""
        samples = self.place(batch, sampling, generator)
        sq_error = 0.0
        for sl in micro_batches(samples.per_ray(), sampling.micro_batch_rays, sampling.micro_batch_samples):
            part_samples = samples.of_rays(sl)
            out = shade_compact(self.tfield, batch.rays_d[sl], batch.params[sl], batch.background[sl], part_samples,
                                sampling.step, sampling.weight_threshold, sampling.density_grads,
                                sampling.colour_sampling)
            part = ((out["rgb"] - batch.target[sl]) ** 2).mean(-1).sum() / batch.divisor
            if not torch.isfinite(part):
                raise FloatingPointError(f"non-finite loss at iteration {iteration}")
            if part.requires_grad:
                part.backward()
            sq_error += float(part.detach())
        return sq_error, len(samples)

    def priors(self, weights: RegularizerWeights,
               merge_marks: Callable[[list[np.ndarray]], None] | None = None) -> dict[str, float]:
        """The priors' gradients and values. The grid priors act at the rows this step touched
        (``row_priors``). With ``merge_marks`` (ranks: ``Ranks.merge_row_marks``, before their
        gradients are averaged) or total variation (which reads a row's neighbours) the tables'
        gradients are materialized, the rows any rank touched marked on every rank, and the
        priors added at the marks; otherwise the optimizer adds the L1 prior as it updates each
        row (its value comes after the step, ``after_step``). The parameter-vector terms (a few
        hundred values) go through autograd."""
        values: dict[str, float] = {}
        density_grads, appearance_grads = self.tfield.row_gradients()
        whole = merge_marks is not None or weights.tv_density > 0 or weights.tv_appearance > 0
        for table in self.tables():
            table.l1_coefficients = None
            if whole:
                table.materialize()
        if merge_marks is not None:
            merge_marks([t.marks for t in self.tables()])
        if weights.l1_density > 0:
            if whole:
                values["l1"] = add_l1_at_marks(self.field.density_grid, density_grads, weights.l1_density)
            else:
                for table in density_grads.tables():
                    table.l1_coefficients = l1_coefficients(table, weights.l1_density)
        if weights.tv_density > 0:
            values["tv_density"] = add_total_variation_at_marks(self.field.density_grid, density_grads,
                                                                weights.tv_density)
        if weights.tv_appearance > 0:
            values["tv_appearance"] = add_total_variation_at_marks(self.field.appearance_grid, appearance_grads,
                                                                   weights.tv_appearance)
        values.update(backward_param_priors(self.field, weights.param_l1, weights.tv_params))
        return values

    def after_step(self) -> dict[str, float]:
        """The L1 prior's value where the optimizer added it (``priors`` without whole gradients)."""
        density_grads, _ = self.tfield.row_gradients()
        if density_grads.plane.l1_coefficients is None:
            return {}
        return {"l1": sum(t.l1_value for t in density_grads.tables())}

    def raw_density(self, coords: Float[Tensor, "m 3"], q: Float[Tensor, "m c"]) -> Float[Tensor, " m"]:
        """The level field ``g`` at grid coordinates with per-point features (``regularizers.level_curvature``)."""
        return self.tfield.raw_density(coords, torch.arange(coords.shape[0]), q)
