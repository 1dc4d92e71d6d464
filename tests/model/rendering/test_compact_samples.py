"""Compact samples (the fused step's layout) against ``renderer.place_samples``: the same points, in
the same order, for every combination of windows, occupancy and jitter; selection by rays and masks."""

import pytest
import torch

from visnerf.config import FieldConfig
from visnerf.rendering import compact_samples
from visnerf.rendering.compact_samples import place_compact
from visnerf.rendering.training_render import place_samples
from visnerf.representation.field import VisNerfField


@pytest.fixture()
def setup():
    g = torch.Generator().manual_seed(0)
    aabb = torch.tensor([[-1.0, -0.8, -0.6], [0.9, 1.0, 0.7]])
    field = VisNerfField(FieldConfig(resolution=(8, 8, 8)), aabb)
    n = 300
    origins = torch.randn(n, 3, generator=g) * 3
    directions = torch.nn.functional.normalize(torch.randn(n, 3, generator=g) - origins * 0.3, dim=-1)
    directions[0] = torch.tensor([0.0, 0.0, 1.0])  # axis-parallel
    origins[0] = torch.tensor([0.1, 0.2, -3.0])
    occupancy = torch.rand(10, 12, 9, generator=g) < 0.5
    windows = (torch.randint(-2, 10, (n,), generator=g), torch.randint(5, 40, (n,), generator=g))
    return field, origins, directions, occupancy, windows


@pytest.mark.parametrize("use_windows", [False, True])
@pytest.mark.parametrize("use_occupancy", [False, True])
@pytest.mark.parametrize("jitter", [False, True])
@pytest.mark.parametrize("threads", [1, 3])
def test_compact_samples_are_the_padded_ones_in_order(setup, use_windows: bool, use_occupancy: bool,
                                                      jitter: bool, threads: int,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """Placed on one thread or in three ranges of rays (then packed), the same samples."""
    field, origins, directions, occupancy, windows = setup
    occ = occupancy if use_occupancy else None
    win = windows if use_windows else None
    gens = [torch.Generator().manual_seed(3) if jitter else None for _ in range(2)]
    padded = place_samples(field, origins, directions, 0.05, 1024, occ, gens[0], win)
    monkeypatch.setattr(compact_samples, "MIN_RAYS_A_PART", 16)
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        compact = place_compact(field.aabb, origins, directions, 0.05, 1024, occ, gens[1], win)
    finally:
        torch.set_num_threads(previous)
    assert len(compact) > 100
    assert torch.equal(compact.points, padded.points[padded.valid])  # bit for bit
    assert torch.equal(compact.per_ray(), padded.valid.sum(dim=1))
    rays = torch.arange(origins.shape[0])[:, None].expand_as(padded.valid)[padded.valid]
    assert torch.equal(compact.ray, rays)
    assert int(compact.offsets[0]) == 0 and torch.equal(compact.offsets[1:], padded.valid.sum(dim=1).cumsum(0))


def test_selecting_rays_and_samples_keeps_the_layout(setup) -> None:
    field, origins, directions, occupancy, _ = setup
    compact = place_compact(field.aabb, origins, directions, 0.05, 1024, occupancy)
    part = compact.of_rays(slice(10, 40))
    assert part.n_rays == 30 and int(part.offsets[0]) == 0
    assert torch.equal(part.points, compact.points[int(compact.offsets[10]):int(compact.offsets[40])])
    assert torch.equal(part.per_ray(), compact.per_ray()[10:40])
    kept = torch.rand(len(compact), generator=torch.Generator().manual_seed(1)) < 0.5
    sigma = torch.arange(len(compact), dtype=torch.float32)
    fewer = compact.keep(kept, sigma)
    assert torch.equal(fewer.points, compact.points[kept]) and torch.equal(fewer.sigma, sigma[kept])
    assert torch.equal(fewer.ray, compact.ray[kept]) and int(fewer.offsets[-1]) == int(kept.sum())
