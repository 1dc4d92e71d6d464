"""A training step split into micro-batches is the same step as one pass over the batch."""

import math

import pytest
import torch

import visnerf.training.fused_step as fused_step_module
import visnerf.training.step as trainer_module
from visnerf.config import TrainConfig
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.training_render import place_samples, render_rays
from visnerf.testing import make_noise_scene
from visnerf.training.ray_batches import micro_batches
from visnerf.training.step import occupied_windows
from visnerf.training.trainer import Trainer


def _occupied_ball() -> torch.Tensor:
    """A ball of occupied cells in the middle of an 8^3 grid."""
    c = (torch.arange(8) + 0.5) / 8 - 0.5
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    return (x**2 + y**2 + z**2).sqrt() < 0.3


def _gradients(
    micro_rays: int, micro_samples: int, monkeypatch: pytest.MonkeyPatch, occupancy: torch.Tensor | None = None,
    fused: bool = False,
) -> dict[str, torch.Tensor]:
    """One step's gradients (the optimizer step skipped), and how many micro-batches it took. The
    batch's stratified positions are placed once for the whole batch, so any split shades the
    same samples."""
    cfg = TrainConfig(iterations=1, batch_rays=256, resolution_init=12, resolution_final=12, carve=False,
                      mixed_precision=False, micro_batch_rays=micro_rays, micro_batch_samples=micro_samples,
                      density_grad_keep=1.0)
    trainer = Trainer(make_noise_scene(), None, cfg, torch.device("cpu"), fused=fused)
    trainer.field.set_occupancy(occupancy)
    trainer.optimizer.step = lambda: None  # keep the gradients, change nothing
    chunks: list[list[slice]] = []
    module = fused_step_module if fused else trainer_module
    monkeypatch.setattr(module, "micro_batches", lambda *args: chunks.append(micro_batches(*args)) or chunks[-1])
    trainer.train_step()
    if trainer.fused is not None:  # the tables' gradients as pending taps: into .grad
        for table in trainer.fused.tables():
            table.materialize()
    grads = {name: p.grad.clone() for name, p in trainer.field.named_parameters() if p.grad is not None}
    grads["micro-batches"] = torch.tensor(len(chunks[0]))
    return grads


def _assert_same_step(whole: dict[str, torch.Tensor], split: dict[str, torch.Tensor]) -> None:
    assert int(whole.pop("micro-batches")) == 1 and int(split.pop("micro-batches")) > 3
    assert whole.keys() == split.keys() and len(whole) > 0
    for name in whole:
        assert torch.allclose(whole[name], split[name], rtol=1e-4, atol=1e-7), name


@pytest.mark.parametrize("fused", [False, True], ids=["torch", "fused"])
def test_micro_batched_gradients_equal_the_whole_batch(monkeypatch: pytest.MonkeyPatch, fused: bool) -> None:
    _assert_same_step(_gradients(10_000, 10**9, monkeypatch, fused=fused),
                      _gradients(37, 2_000, monkeypatch, fused=fused))


@pytest.mark.parametrize("fused", [False, True], ids=["torch", "fused"])
def test_micro_batched_gradients_equal_the_whole_batch_when_chunks_count_occupied_samples(
    monkeypatch: pytest.MonkeyPatch, fused: bool
) -> None:
    _assert_same_step(_gradients(10_000, 10**9, monkeypatch, _occupied_ball(), fused),
                      _gradients(10_000, 25, monkeypatch, _occupied_ball(), fused))  # a few samples a chunk: > 3 chunks


def test_micro_batches_hold_the_samples_each_ray_evaluates_within_both_budgets() -> None:
    """Chunks are counted by the samples each ray evaluates (in occupied cells), not by its span:
    every chunk holds at most the budget (or a single ray), they tile the batch in order, and with
    content in a small part of the box they are far fewer than chunks counted along the box span."""
    scene = make_noise_scene()
    field = Trainer(scene, None, TrainConfig(carve=False, resolution_init=12), torch.device("cpu")).field
    field.set_occupancy(_occupied_ball())
    g = torch.Generator().manual_seed(3)
    origins = torch.randn(600, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 2.0])
    dirs = torch.nn.functional.normalize(-origins + 0.4 * torch.randn(600, 3, generator=g), dim=-1)
    step, budget = 0.02, 800
    placed = place_samples(field, origins, dirs, step, 1024, field.occupancy, torch.Generator().manual_seed(0))
    in_box = place_samples(field, origins, dirs, step, 1024, None, torch.Generator().manual_seed(0))
    per_ray = placed.per_ray()
    assert int(per_ray.sum()) < 0.5 * int(in_box.per_ray().sum())
    for max_rays in (10_000, 64):
        slices = micro_batches(per_ray, max_rays, budget)
        assert slices[0].start == 0 and slices[-1].stop == 600
        assert all(a.stop == b.start for a, b in zip(slices, slices[1:], strict=False))  # contiguous, in order
        for sl in slices:
            assert sl.stop - sl.start <= max_rays
            assert int(per_ray[sl].sum()) <= budget or sl.stop - sl.start == 1
            # the next ray would not have fitted: the chunks are as full as the budgets allow
            if sl.stop < 600:
                assert sl.stop - sl.start == max_rays or int(per_ray[sl.start:sl.stop + 1].sum()) > budget
    by_box = micro_batches(in_box.per_ray(), 10_000, budget)
    assert len(micro_batches(per_ray, 10_000, budget)) < 0.6 * len(by_box)


def test_a_single_ray_above_the_sample_budget_is_a_micro_batch_of_its_own() -> None:
    per_ray = torch.tensor([5, 50, 5, 5, 0, 7])
    assert micro_batches(per_ray, 10, 20) == [slice(0, 1), slice(1, 2), slice(2, 6)]
    assert micro_batches(per_ray, 2, 10**6) == [slice(0, 2), slice(2, 4), slice(4, 6)]
    assert micro_batches(torch.zeros(0, dtype=torch.long), 4, 4) == []
    assert micro_batches(per_ray, 6, 72) == [slice(0, 6)]  # everything fits: one micro-batch
    assert micro_batches(per_ray, 6, 71) == [slice(0, 5), slice(5, 6)]
    assert micro_batches(per_ray, 5, 72) == [slice(0, 5), slice(5, 6)]


def test_windowed_positions_shade_like_positions_along_the_whole_box_span() -> None:
    """The occupied window leaves out only samples in empty cells: the same samples evaluated and
    the same colours as sampling the whole box span, for the same jitter."""
    scene = make_noise_scene()
    field = Trainer(scene, None, TrainConfig(carve=False, resolution_init=12), torch.device("cpu")).field
    field.set_occupancy(_occupied_ball())
    g = torch.Generator().manual_seed(3)
    origins = torch.randn(300, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 2.0])
    dirs = torch.nn.functional.normalize(-origins + 0.4 * torch.randn(300, 3, generator=g), dim=-1)
    params, bg, step = torch.zeros(300, 1), torch.ones(300, 3), 0.02
    windows = occupied_windows(field, origins, dirs, step, EmptySpace.of(field.occupancy, field.aabb))
    with torch.no_grad():
        for seed in range(3):
            everything = render_rays(field, origins, dirs, params, bg, step, 1024, field.occupancy,
                                     generator=torch.Generator().manual_seed(seed))
            windowed = render_rays(field, origins, dirs, params, bg, step, 1024, field.occupancy,
                                   generator=torch.Generator().manual_seed(seed), windows=windows)
            assert int(windowed["n_samples"]) == int(everything["n_samples"]) > 0
            assert torch.allclose(windowed["rgb"], everything["rgb"], atol=1e-6)


def test_a_step_whose_rays_meet_no_occupied_cell_does_not_fail() -> None:
    """Seen in a time-budgeted run: after an occupancy update every ray of one micro-batch missed
    the occupied cells, its loss had no graph and ``backward`` raised."""
    cfg = TrainConfig(iterations=1, batch_rays=128, resolution_init=12, resolution_final=12, carve=False,
                      mixed_precision=False, micro_batch_rays=32)
    trainer = Trainer(make_noise_scene(), None, cfg, torch.device("cpu"))
    trainer.field.set_occupancy(torch.zeros(8, 8, 8, dtype=torch.bool))  # nothing occupied
    before = {n: p.detach().clone() for n, p in trainer.field.named_parameters()}
    stats = trainer.train_step()
    assert all(math.isfinite(float(v)) for v in stats.values() if isinstance(v, float))
    grid_names = [n for n in before if "grid" in n or "decoder" in n]
    assert grid_names
    for name in grid_names:  # only the regularisers can move them; the photometric loss did not fail
        assert torch.isfinite(dict(trainer.field.named_parameters())[name]).all()
