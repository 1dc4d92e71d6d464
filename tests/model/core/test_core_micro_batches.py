"""A training step split into micro-batches is the same step as one pass over the batch."""

import math

import pytest
import torch

import visnerf.training.trainer as trainer_module
from visnerf.config import TrainConfig
from visnerf.testing import make_noise_scene
from visnerf.training.trainer import Trainer, micro_batches, occupied_windows


def _occupied_ball() -> torch.Tensor:
    """A ball of occupied cells in the middle of an 8^3 grid."""
    c = (torch.arange(8) + 0.5) / 8 - 0.5
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    return (x**2 + y**2 + z**2).sqrt() < 0.3


def _gradients(
    micro_rays: int, micro_samples: int, monkeypatch: pytest.MonkeyPatch, occupancy: torch.Tensor | None = None
) -> dict[str, torch.Tensor]:
    original = trainer_module.render_rays

    def deterministic(*args, **kwargs):  # midpoint samples, so every split sees the same positions
        args = list(args)
        args[9] = None  # generator
        return original(*args, **kwargs)

    monkeypatch.setattr(trainer_module, "render_rays", deterministic)
    cfg = TrainConfig(iterations=1, batch_rays=256, resolution_init=12, resolution_final=12, carve=False,
                      mixed_precision=False, micro_batch_rays=micro_rays, micro_batch_samples=micro_samples)
    trainer = Trainer(make_noise_scene(), None, cfg, torch.device("cpu"))
    trainer.field.set_occupancy(occupancy)
    trainer.optimizer.step = lambda: None  # keep the gradients, change nothing
    trainer.train_step()
    return {name: p.grad.clone() for name, p in trainer.field.named_parameters() if p.grad is not None}


def test_micro_batched_gradients_equal_the_whole_batch(monkeypatch: pytest.MonkeyPatch) -> None:
    whole = _gradients(10_000, 10**9, monkeypatch)
    split = _gradients(37, 2_000, monkeypatch)
    assert whole.keys() == split.keys() and len(whole) > 0
    for name in whole:
        assert torch.allclose(whole[name], split[name], rtol=1e-4, atol=1e-7), name


def test_micro_batched_gradients_equal_the_whole_batch_when_chunks_count_occupied_samples(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    whole = _gradients(10_000, 10**9, monkeypatch, _occupied_ball())
    split = _gradients(37, 300, monkeypatch, _occupied_ball())
    assert whole.keys() == split.keys() and len(whole) > 0
    for name in whole:
        assert torch.allclose(whole[name], split[name], rtol=1e-4, atol=1e-7), name


def test_chunks_counted_by_occupied_span_hold_the_samples_evaluated_within_the_budget() -> None:
    """Counting each ray's occupied span (plus the jitter's sample at each end) instead of its
    box span: every chunk's evaluated samples, stratified, stay within the budget, with fewer chunks."""
    from visnerf.rendering.empty_space import EmptySpace
    from visnerf.rendering.renderer import render_rays

    scene = make_noise_scene()
    field = Trainer(scene, None, TrainConfig(carve=False, resolution_init=12), torch.device("cpu")).field
    field.set_occupancy(_occupied_ball())
    g = torch.Generator().manual_seed(3)
    origins = torch.randn(600, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 2.0])
    dirs = torch.nn.functional.normalize(-origins + 0.4 * torch.randn(600, 3, generator=g), dim=-1)
    step, budget = 0.02, 800
    space = EmptySpace.of(field.occupancy, field.aabb)
    by_box = micro_batches(field, origins, dirs, step, max_rays=10_000, max_samples=budget)
    windows = occupied_windows(field, origins, dirs, step, space)
    by_span = micro_batches(field, origins, dirs, step, max_rays=10_000, max_samples=budget, windows=windows)
    assert by_span[0].start == 0 and by_span[-1].stop == 600
    assert all(a.stop == b.start for a, b in zip(by_span, by_span[1:], strict=False))
    assert len(by_span) < 0.6 * len(by_box)
    params = torch.zeros(600, 1)
    bg = torch.ones(600, 3)
    with torch.no_grad():
        for sl in by_span:
            for seed in range(3):
                everything = render_rays(field, origins[sl], dirs[sl], params[sl], bg[sl], step, 1024,
                                         field.occupancy, generator=torch.Generator().manual_seed(seed))
                windowed = render_rays(field, origins[sl], dirs[sl], params[sl], bg[sl], step, 1024,
                                       field.occupancy, generator=torch.Generator().manual_seed(seed),
                                       windows=(windows[0][sl], windows[1][sl]))
                assert int(everything["n_samples"]) <= budget or sl.stop - sl.start == 1
                # the window leaves out only samples in empty cells: the same colours
                assert int(windowed["n_samples"]) == int(everything["n_samples"])
                assert torch.allclose(windowed["rgb"], everything["rgb"], atol=1e-6)


def test_micro_batches_cover_the_batch_within_both_budgets() -> None:
    scene = make_noise_scene()
    field = Trainer(scene, None, TrainConfig(carve=False, resolution_init=12), torch.device("cpu")).field
    g = torch.Generator().manual_seed(1)
    origins = torch.randn(500, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 2.0])
    dirs = torch.nn.functional.normalize(-origins + 0.3 * torch.randn(500, 3, generator=g), dim=-1)
    step = 0.02
    slices = micro_batches(field, origins, dirs, step, max_rays=64, max_samples=1500)
    assert slices[0].start == 0 and slices[-1].stop == 500
    assert all(a.stop == b.start for a, b in zip(slices, slices[1:], strict=False))  # contiguous
    from visnerf.rendering.aabb import intersect_aabb

    t_near, t_far, hit = intersect_aabb(origins, dirs, field.aabb)
    per_ray = torch.where(hit, ((t_far - t_near).clamp_min(0) / step).ceil(), torch.zeros_like(t_far))
    for sl in slices:
        assert sl.stop - sl.start <= 64
        assert per_ray[sl].sum() <= 1500 or sl.stop - sl.start == 1


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
