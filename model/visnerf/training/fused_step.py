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

from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from torch import Tensor

from visnerf.rendering.colour_sampling import ColourSampling
from visnerf.rendering.compact_render import drop_occluded_compact, shade_compact
from visnerf.rendering.compact_samples import CompactSamples, place_compact
from visnerf.rendering.density_gradients import DensityGradientSampling
from visnerf.representation.field import VisNerfField
from visnerf.representation.training_field import TrainingField
from visnerf.training.ray_batches import micro_batches
from visnerf.training.regularizers import RegularizerWeights, regularization
from visnerf.training.row_priors import add_l1_at_marks, add_total_variation_at_marks
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
    """The fused path of one field: its ``TrainingField`` and the optimizer's row marks."""

    def __init__(self, field: VisNerfField, optimizer: RowSparseAdam) -> None:
        self.field = field
        self.tfield = TrainingField(field)
        for grid, grads in ((field.density_grid, self.tfield.density_grads),
                            (field.appearance_grid, self.tfield.appearance_grads)):
            planes, lines = grid.row_tables()
            optimizer.set_row_marks(planes, grads.plane_marks)
            optimizer.set_row_marks(lines, grads.line_marks)

    def follows(self, field: VisNerfField) -> bool:
        return self.tfield.follows(field)

    def row_marks(self) -> list:
        return [m for g in self.tfield.row_gradients() for m in (g.plane_marks, g.line_marks)]

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

    def priors(self, weights: RegularizerWeights) -> dict[str, float]:
        """The priors' gradients: the grid terms at the rows this step touched (``row_priors``),
        the parameter-vector terms (a few hundred values) through autograd; their values."""
        values: dict[str, float] = {}
        density_grads, appearance_grads = self.tfield.row_gradients()
        if weights.l1_density > 0:
            values["l1"] = add_l1_at_marks(self.field.density_grid, density_grads, weights.l1_density)
        if weights.tv_density > 0:
            values["tv_density"] = add_total_variation_at_marks(self.field.density_grid, density_grads,
                                                                weights.tv_density)
        if weights.tv_appearance > 0:
            values["tv_appearance"] = add_total_variation_at_marks(self.field.appearance_grid, appearance_grads,
                                                                   weights.tv_appearance)
        rest = regularization(self.field, RegularizerWeights(0.0, weights.param_l1, 0.0, 0.0, weights.tv_params))
        if rest:
            sum(rest.values()).backward()
            values.update({k: float(v.detach()) for k, v in rest.items()})
        return values

    def raw_density(self, coords: Float[Tensor, "m 3"], q: Float[Tensor, "m c"]) -> Float[Tensor, " m"]:
        """The level field ``g`` at grid coordinates with per-point features (``regularizers.level_curvature``)."""
        return self.tfield.raw_density(coords, torch.arange(coords.shape[0]), q)
