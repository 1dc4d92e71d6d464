"""A few training steps on fixed global batches, run by ``test_distributed_training.py`` under torchrun.

Every rank builds the same trainer (same seed, same field), joins the ranks and trains on fixed
global batches of ``BATCH`` rays, drawn up front by a seeded sampler, the same on every rank; rank
``r`` of ``N`` takes rays ``[r * BATCH / N, (r + 1) * BATCH / N)`` of each. The run upsamples its
grid once on the way (a milestone, after which rank 0's field is broadcast). Each rank writes its
final parameters and its first and last step's (averaged) gradients to ``OUT/rank<r>.safetensors``,
with ``stopped_at`` (iteration, stopped) of a second run that only the last rank is asked to stop
before step 2; rank 0 then trains a fresh trainer alone, on the whole batches, and writes
``OUT/solo.safetensors`` and the starting parameters ``OUT/init.safetensors``.

Stratified jitter (one random offset per ray, drawn from each rank's own stream) is the one draw that
cannot be split between ranks the way it is drawn by one process, so samples sit at the midpoints of
their steps here; random backgrounds and sampled density gradients are off for the same reason, and
the decoders multiply in float32 (bfloat16 products round differently as the batch is cut).
The second argument names the step: ``torch`` (its gradients are kept too) or ``fused``, whose
table gradients the optimizer consumes (only the parameters are compared).
"""

import sys
from pathlib import Path

import torch
from safetensors.torch import save_file

import visnerf.training.fused_step as fused_step_module
import visnerf.training.step as step_module
from visnerf.config import FieldConfig, TrainConfig
from visnerf.testing import make_noise_scene
from visnerf.training.distributed import Launch, Ranks, run_then_leave
from visnerf.training.ray_batches import RayBatch, RayBatchSampler
from visnerf.training.trainer import Trainer

BATCH = 512
STEPS = 4
CONFIG = TrainConfig(iterations=STEPS, batch_rays=BATCH, micro_batch_rays=96, resolution_init=10, resolution_final=14,
                     upsample_at=(0.5,), carve=False, density_grad_keep=1.0, stop_eps=0.0,
                     weight_average_span=0.0, mixed_precision=False, seed=3)
FIELD = FieldConfig(n_density_components=4, n_appearance_components=8, hidden_width=16)


def midpoint_samples(field, rays_o, rays_d, step, max_samples, occupancy, generator=None, windows=None):
    """``place_samples`` without its stratified jitter."""
    return place_samples(field, rays_o, rays_d, step, max_samples, occupancy, None, windows)


def midpoint_compact(aabb, rays_o, rays_d, step, max_samples, occupancy, generator=None, windows=None):
    """``place_compact`` without its stratified jitter."""
    return place_compact(aabb, rays_o, rays_d, step, max_samples, occupancy, None, windows)


place_samples = step_module.place_samples
step_module.place_samples = midpoint_samples
place_compact = fused_step_module.place_compact
fused_step_module.place_compact = midpoint_compact
FUSED = len(sys.argv) > 2 and sys.argv[2] == "fused"


class FixedBatches:
    """Stands in for the trainer's sampler: this rank's rays of the next fixed global batch."""

    def __init__(self, batches: list[RayBatch], rank: int, world_size: int) -> None:
        self.batches, self.rank, self.world_size, self.step = batches, rank, world_size, 0

    def set_aabb(self, aabb: torch.Tensor | None) -> None:
        pass

    def sample(self, n: int) -> RayBatch:
        assert n * self.world_size == BATCH, n
        batch = self.batches[self.step]
        self.step += 1
        part = slice(self.rank * n, (self.rank + 1) * n)
        return RayBatch(*(getattr(batch, name)[part] for name in RayBatch.__dataclass_fields__))


class GradientTrainer(Trainer):
    """Keeps each step's gradients (the ranks' average), as the optimizer used them."""

    def train_step(self) -> dict[str, float]:
        stats = super().train_step()
        self.gradients = {} if FUSED else {name: p.grad.clone() for name, p in self.field.named_parameters()
                                           if p.grad is not None}
        self.first_gradients = getattr(self, "first_gradients", self.gradients)
        return stats


class StopOnLastRank:
    """A stop request (``StopRequest``) that only the last rank receives, before step ``at``."""

    def __init__(self, trainer: Trainer, at: int) -> None:
        self.trainer, self.at = trainer, at

    def requested(self) -> bool:
        ranks = self.trainer.ranks
        return ranks.rank == ranks.world_size - 1 and self.trainer.state.iteration >= self.at

    def loop_ended(self) -> None:
        pass


def train(batches: list[RayBatch], ranks: Ranks, stop_at: int | None = None) -> GradientTrainer:
    trainer = GradientTrainer(make_noise_scene(n_views=6, size=16), None, CONFIG, ranks.device, field_cfg=FIELD,
                              fused=FUSED)
    trainer.distribute(ranks)
    trainer.sampler = FixedBatches(batches, ranks.rank, ranks.world_size)  # type: ignore[assignment]
    trainer.run(progress_bar=False, stop=None if stop_at is None else StopOnLastRank(trainer, stop_at))
    return trainer


def parameters(trainer: Trainer) -> dict[str, torch.Tensor]:
    return {name: p.detach().clone().contiguous() for name, p in trainer.field.named_parameters()}


def results(trainer: GradientTrainer) -> dict[str, torch.Tensor]:
    """Final parameters, the first and the last step's gradients."""
    return {**parameters(trainer), **{f"grad0.{k}": g for k, g in trainer.first_gradients.items()},
            **{f"grad.{k}": g for k, g in trainer.gradients.items()}}


def main(out: Path) -> int:
    device = torch.device("cpu")
    scene = make_noise_scene(n_views=6, size=16)
    sampler = RayBatchSampler(scene, device, torch.Generator().manual_seed(11))
    sampler.set_aabb(scene.bbox)
    batches = [sampler.sample(BATCH) for _ in range(STEPS)]
    ranks = Ranks.start(Launch.from_environment(), device)

    def ranks_part() -> None:
        trainer = train(batches, ranks)
        stopped = train(batches, ranks, stop_at=2)  # every rank stops where the last one is asked to
        stop = {"stopped_at": torch.tensor([stopped.state.iteration, int(stopped.stopped)])}
        save_file({**results(trainer), **stop}, str(out / f"rank{ranks.rank}.safetensors"))

    run_then_leave(ranks_part)  # as ``visnerf train`` leaves its process group
    if ranks.is_main:
        solo = Trainer(scene, None, CONFIG, device, field_cfg=FIELD, fused=FUSED)
        save_file(parameters(solo), str(out / "init.safetensors"))
        save_file(results(train(batches, Ranks.solo(device))), str(out / "solo.safetensors"))
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1])))
