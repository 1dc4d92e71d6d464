"""Training pixels drawn where the model errs (``data/error_map.py``) and weighted by their inverse
probability, against closed forms and the uniform draw."""

import math

import pytest
import torch

from visnerf.config import TrainConfig
from visnerf.data.error_map import ErrorMapConfig, PixelErrorMap
from visnerf.data.ray_batches import RayBatchSampler
from visnerf.testing import make_noise_scene
from visnerf.training.trainer import Trainer


def _map_with_errors(uniform: float = 0.25) -> tuple[PixelErrorMap, torch.Tensor]:
    """Two 10x7 frames in 4-pixel tiles (the last row and column of tiles are partial: 2 and 3 pixels)."""
    m = PixelErrorMap(2, 10, 7, ErrorMapConfig(tile=4, uniform=uniform))
    errors = torch.tensor([0.0, 0.01, 0.04, 0.09, 0.16, 0.25, 0.36, 0.49, 0.64, 0.81, 1.0, 0.0])
    m.error = errors.clone()
    m.visited[:] = True
    return m, errors


def test_tile_masses_are_the_root_error_share_plus_the_uniform_share() -> None:
    m, errors = _map_with_errors(uniform=0.25)
    pixels = torch.tensor([16.0, 12.0, 16.0, 12.0, 8.0, 6.0] * 2)  # 4x4, 4x3, ..., 2x3
    assert torch.equal(m.pixels_all, pixels) and float(pixels.sum()) == 2 * 10 * 7
    root = errors.double().sqrt() * pixels.double()
    expected = 0.75 * root / root.sum() + 0.25 * pixels.double() / 140.0
    assert torch.allclose(m.tile_masses().double(), expected, rtol=1e-6, atol=0)
    assert math.isclose(float(m.tile_masses().sum()), 1.0, rel_tol=1e-6)


def test_a_map_of_zero_errors_draws_every_pixel_alike() -> None:
    m, _ = _map_with_errors()
    m.error.zero_()
    masses = m.tile_masses()
    assert torch.allclose(masses, m.pixels_all / 140.0)
    _, _, _, weight = m.draw(1000, torch.Generator().manual_seed(0))
    assert torch.allclose(weight, torch.ones(1000), rtol=1e-6)


def test_draws_follow_the_masses_and_stay_inside_their_tiles() -> None:
    m, _ = _map_with_errors()
    n = 200_000
    frame, px, py, weight = m.draw(n, torch.Generator().manual_seed(1))
    assert bool(((0 <= px) & (px < 7) & (0 <= py) & (py < 10) & (0 <= frame) & (frame < 2)).all())
    tile = m.tile_of(frame, px, py)
    counts = torch.bincount(tile, minlength=12).double()
    p = m.tile_masses().double()
    sd = (n * p * (1 - p)).sqrt()
    assert bool(((counts - n * p).abs() <= 5 * sd + 1).all()), (counts / n, p)
    # Within a tile, pixels are alike: the 16 pixels of tile 8 (frame 1's first tile) each get 1/16.
    in_tile = (frame == 1) & (px < 4) & (py < 4)
    per_pixel = torch.bincount((py[in_tile] * 4 + px[in_tile]), minlength=16).double() / float(in_tile.sum())
    assert bool(((per_pixel - 1 / 16).abs() < 0.01).all())
    # The weight is 1 / (pixels * p(pixel)), p(pixel) = its tile's mass over the tile's pixels.
    expected = m.pixels_all[tile].double() / (140.0 * p[tile])
    assert torch.allclose(weight.double(), expected, rtol=1e-5)


def test_the_weighted_mean_is_an_unbiased_estimate_of_the_uniform_mean() -> None:
    """The mean of ``w * e`` over drawn pixels against the mean of ``e`` over all pixels, for a
    per-pixel ``e`` the map's tiles know nothing of (400000 draws: standard error under 0.1 %)."""
    m, _ = _map_with_errors(uniform=0.2)
    e = torch.rand(2, 10, 7, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    frame, px, py, weight = m.draw(400_000, torch.Generator().manual_seed(6))
    values = weight.double() * e[frame, py, px]
    estimate, stderr = float(values.mean()), float(values.std() / math.sqrt(values.numel()))
    assert abs(estimate - float(e.mean())) < 4 * stderr


def test_weights_are_bounded_by_the_inverse_uniform_share() -> None:
    m, _ = _map_with_errors(uniform=0.25)
    _, _, _, weight = m.draw(50_000, torch.Generator().manual_seed(2))
    assert float(weight.max()) <= 1 / 0.25 + 1e-5


def test_recording_replaces_the_first_estimate_then_averages_and_ignores_non_finite_errors() -> None:
    m = PixelErrorMap(1, 8, 8, ErrorMapConfig(tile=4, smoothing=0.5))
    assert torch.equal(m.error, torch.ones(4))  # unvisited tiles start at the largest error
    frame, px, py = torch.tensor([0]), torch.tensor([5]), torch.tensor([1])  # tile 1
    m.record(frame, px, py, torch.tensor([0.2]))
    assert m.error.tolist() == pytest.approx([1.0, 0.2, 1.0, 1.0])
    m.record(frame, px, py, torch.tensor([0.4]))
    assert m.error[1].item() == pytest.approx(0.3)
    m.record(frame, px, py, torch.tensor([math.nan]))
    m.record(torch.tensor([0]), torch.tensor([0]), torch.tensor([7]), torch.tensor([math.inf]))
    assert m.error.tolist() == pytest.approx([1.0, 0.3, 1.0, 1.0]) and m.visited.tolist() == [False, True, False, False]


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"tile": 0}, "tile"),
    ({"uniform": 0.0}, "uniform"),
    ({"uniform": 1.5}, "uniform"),
    ({"smoothing": 0.0}, "smoothing"),
    ({"refresh_every": 0}, "refresh_every"),
])
def test_unusable_map_settings_are_refused(kwargs, message) -> None:
    with pytest.raises(ValueError, match=message):
        ErrorMapConfig(**kwargs)


@pytest.mark.parametrize(("field", "value"), [("error_sampling_tile", -1), ("error_sampling_uniform", 0.0),
                                              ("error_sampling_uniform", 2.0)])
def test_unusable_training_settings_are_refused(field, value) -> None:
    with pytest.raises(ValueError, match=field):
        TrainConfig(**{field: value})


def test_batches_weigh_alike_without_a_map_and_average_one_with_it() -> None:
    scene = make_noise_scene(n_views=4, size=16)
    uniform = RayBatchSampler(scene, torch.device("cpu"), torch.Generator().manual_seed(0))
    batch = uniform.sample(256)
    assert torch.equal(batch.weight, torch.ones(256))
    error_map = PixelErrorMap(4, 16, 16, ErrorMapConfig(tile=2))
    error_map.error = torch.rand(error_map.error.numel(), generator=torch.Generator().manual_seed(1))
    error_map.visited[:] = True
    drawn = RayBatchSampler(scene, torch.device("cpu"), torch.Generator().manual_seed(0), error_map).sample(256)
    assert math.isclose(float(drawn.weight.mean()), 1.0, rel_tol=1e-5) and float(drawn.weight.std()) > 0.05
    # Each ray's colour is its drawn pixel's.
    expected = scene.images[drawn.frame, drawn.py, drawn.px].float() / 255.0
    assert torch.equal(drawn.rgb, expected)


def test_a_redrawn_pixel_is_recorded_with_its_background_error() -> None:
    scene = make_noise_scene(n_views=2, size=16)
    error_map = PixelErrorMap(2, 16, 16, ErrorMapConfig(tile=1))
    sampler = RayBatchSampler(scene, torch.device("cpu"), torch.Generator().manual_seed(0), error_map)
    sampler.set_aabb(torch.tensor([[-0.05, -0.05, -0.05], [0.05, 0.05, 0.05]]))  # most rays miss it
    sampler.sample(64)
    assert bool(error_map.visited.any())
    tiles = error_map.visited.nonzero()[:, 0]
    frame, rest = tiles // 256, tiles % 256
    py, px = rest // 16, rest % 16
    rgb = scene.images[frame, py, px].float() / 255.0
    background = ((rgb - torch.tensor(scene.background)) ** 2).mean(-1)
    assert torch.allclose(error_map.error[tiles], background)


def test_training_with_the_map_measures_the_pixels_it_draws() -> None:
    scene = make_noise_scene(n_views=4, size=16)
    cfg = TrainConfig(iterations=4, batch_rays=128, resolution_init=16, resolution_final=16, upsample_at=(),
                      occupancy_at=(), carve=False, validate_every_s=1e9, choose_full_spacing=False,
                      error_sampling_tile=2)
    trainer = Trainer(scene, None, cfg, torch.device("cpu"))
    stats = trainer.train_step()
    error_map = trainer.sampler.error_map
    assert error_map is not None and math.isfinite(stats["mse"])
    visited = int(error_map.visited.sum())
    assert 0 < visited <= 128 and bool((error_map.error[error_map.visited] < 1.0).all())
