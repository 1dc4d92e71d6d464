"""The fused step's render (compact samples, compiled lookups and compositing) against the torch path,
its slow twin, in float64: the same samples, colours, loss and gradient of every parameter, on every
kind of field (K = 0 to 3, a level axis, facing cosines, opaque surfaces whose occluded samples are
dropped), with the near-empty densities and light colours sampled at random by the same draws."""

import copy

import pytest
import torch

from visnerf.rendering.colour_sampling import ColourSampling
from visnerf.rendering.compact_render import drop_occluded_compact, shade_compact
from visnerf.rendering.compact_samples import place_compact
from visnerf.rendering.density_gradients import DensityGradientSampling
from visnerf.rendering.training_render import drop_occluded, place_samples, shade_rays
from visnerf.representation.training_field import TrainingField
from visnerf.testing import make_tiny_field

AXES = {
    0: [],
    1: [("a", [0.0, 0.5, 1.0])],
    2: [("a", [0.0, 0.5, 1.0]), ("b", [0.0, 1.0])],
    3: [("a", [0.0, 0.5, 1.0]), ("b", [0.0, 1.0]), ("c", [0.0, 0.3, 0.6, 1.0])],
}
KINDS = {
    "volume K=0": (0, {}, 0.0),
    "volume K=1": (1, {}, 0.0),
    "volume K=2": (2, {}, 0.0),
    "volume K=3": (3, {}, 0.0),
    "surface, facing cosines, occluded dropped": (2, {"facing_vectors": 2, "density_scale": 20.0}, 1e-2),
    "level axis": (2, {"level_set_axis": 0, "level_cosine_powers": (4, 16), "density_scale": 20.0}, 1e-3),
}


def rays(n: int, k: int, seed: int) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.2 + torch.tensor([0.0, 0.0, -2.0], dtype=torch.float64)
    targets = torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    params = torch.rand(n, k, generator=g, dtype=torch.float64) * 2 - 1
    colours = torch.rand(n, 3, generator=g, dtype=torch.float64)
    background = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return origins, directions, params, colours, background


def gradients(field) -> dict[str, torch.Tensor]:
    return {name: p.grad.clone() for name, p in field.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}


@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.parametrize("sampled", [False, True], ids=["every-sample", "sampled-draws"])
def test_fused_render_and_gradients_equal_the_torch_paths(kind: str, sampled: bool) -> None:
    k, options, stop_eps = KINDS[kind]
    field, _ = make_tiny_field(AXES[k], seed=5, resolution=10, **options)
    field = field.double()
    twin = copy.deepcopy(field)
    occupancy = torch.rand(7, 8, 9, generator=torch.Generator().manual_seed(2)) < 0.7
    origins, directions, params, targets, background = rays(64, k, seed=1)
    step = 0.6 * field.voxel_size()

    def draws(seed: int) -> tuple[torch.Generator, DensityGradientSampling | None, ColourSampling | None]:
        g = torch.Generator().manual_seed(seed)
        if not sampled:
            return g, None, None
        return g, DensityGradientSampling(0.05, 0.3, g), ColourSampling(0.05, g)

    g, density_grads, colour_sampling = draws(7)
    samples = place_samples(twin, origins, directions, step, 256, occupancy, g)
    samples = drop_occluded(twin, samples, params, stop_eps)
    out = shade_rays(twin, directions, params, background, samples, 1e-4, density_grads, colour_sampling)
    ((out["rgb"] - targets) ** 2).sum().backward()

    tfield = TrainingField(field)
    g, density_grads, colour_sampling = draws(7)
    compact = place_compact(field.aabb, origins, directions, step, 256, occupancy, g)
    compact = drop_occluded_compact(tfield, compact, params, step, stop_eps)
    fused = shade_compact(tfield, directions, params, background, compact, step, 1e-4, density_grads, colour_sampling)
    ((fused["rgb"] - targets) ** 2).sum().backward()
    for grads in tfield.row_gradients():
        grads.materialize()

    assert len(compact) == int(samples.valid.sum()) > 100
    assert torch.allclose(fused["rgb"], out["rgb"], rtol=0, atol=1e-12)
    assert torch.allclose(fused["opacity"], out["opacity"], rtol=0, atol=1e-12)
    expected, got = gradients(twin), gradients(field)
    assert set(got) == set(expected)
    for name, grad in expected.items():
        scale = float(grad.abs().max())
        assert torch.allclose(got[name], grad, rtol=0, atol=1e-10 * max(1.0, scale)), name


def test_the_marks_hold_every_row_with_a_gradient() -> None:
    field, _ = make_tiny_field(AXES[2], seed=1, resolution=9)
    field = field.double()
    tfield = TrainingField(field)
    origins, directions, params, targets, background = rays(40, 2, seed=3)
    step = 0.5 * field.voxel_size()
    compact = place_compact(field.aabb, origins, directions, step, 256, None, torch.Generator().manual_seed(0))
    out = shade_compact(tfield, directions, params, background, compact, step)
    ((out["rgb"] - targets) ** 2).sum().backward()
    for grads in tfield.row_gradients():
        assert all(len(t.pending) == 1 for t in grads.tables())
        grads.materialize()
        for table in grads.tables():
            touched = table.buffer().abs().sum(dim=1) > 0
            assert bool(torch.from_numpy(table.marks).bool()[touched].all()) and not table.pending
            assert int(table.marks.sum()) > 0
        assert int(grads.plane.marks.sum()) < grads.plane.n_rows  # 40 rays read part of each plane


def test_a_batch_whose_rays_miss_everything_renders_the_background() -> None:
    field, _ = make_tiny_field(AXES[1], seed=0)
    tfield = TrainingField(field)
    origins = torch.tensor([[5.0, 5.0, -3.0], [0.0, 0.0, -3.0]])
    directions = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    background = torch.tensor([[0.2, 0.4, 0.6], [0.1, 0.1, 0.1]])
    empty = torch.zeros(4, 4, 4, dtype=torch.bool)
    compact = place_compact(field.aabb, origins, directions, 0.05, 256, empty, torch.Generator().manual_seed(0))
    assert len(compact) == 0 and compact.per_ray().tolist() == [0, 0]
    out = shade_compact(tfield, directions, torch.zeros(2, 1), background, compact, 0.05)
    assert torch.equal(out["rgb"], background) and torch.equal(out["opacity"], torch.zeros(2))
