"""Rays drawn from the training images' silhouette band (``TrainConfig.silhouette_ray_fraction``):
the band against a pixel-by-pixel reference, and the sampler's share of band rays."""

import dataclasses

import pytest
import torch

from visnerf.config import FieldConfig, TrainConfig
from visnerf.data.carving import foreground_masks
from visnerf.training.ray_batches import RayBatchSampler, silhouette_pixels
from visnerf.training.recipe import choose_recipe
from visnerf.training.trainer import Trainer

WHITE = (1.0, 1.0, 1.0)


def _band_by_loops(fg: torch.Tensor) -> torch.Tensor:
    """The band pixel by pixel: a pixel whose 3x3 window (clipped at the border) holds both."""
    n, h, w = fg.shape
    band = torch.zeros_like(fg)
    for f in range(n):
        for y in range(h):
            for x in range(w):
                window = fg[f, max(y - 1, 0) : y + 2, max(x - 1, 0) : x + 2]
                band[f, y, x] = bool(window.any()) and not bool(window.all())
    return band


def _images(seed: int) -> torch.Tensor:
    """Three 12x10 frames of random blobs on white, with near-white and border-touching content."""
    g = torch.Generator().manual_seed(seed)
    images = torch.full((3, 12, 10, 3), 255, dtype=torch.uint8)
    images[0, 3:7, 2:6] = torch.tensor([200, 120, 40], dtype=torch.uint8)
    images[1, 0:4, 6:10] = 0  # touches two borders: the border is no boundary
    images[1, 8, 3] = 254  # within the tolerance: background
    images[2] = torch.where(torch.rand(12, 10, 1, generator=g) < 0.3, 30, 255).to(torch.uint8)
    return images


@pytest.mark.parametrize("seed", [0, 1])
def test_the_band_equals_the_pixel_by_pixel_reference(seed):
    images = _images(seed)
    fg = foreground_masks(images, WHITE, 2, 0)
    expected = _band_by_loops(fg).reshape(-1).nonzero()[:, 0]
    assert torch.equal(silhouette_pixels(images, WHITE, 2, chunk=2), expected)  # chunks split the frames
    # Frame 1: the square's border rows and columns are content, not band.
    assert not fg[1, 8, 3]
    band = torch.zeros(images.shape[:3], dtype=torch.bool).reshape(-1)
    band[expected] = True
    band = band.view(images.shape[:3])
    assert not bool(band[1, 0, 9]) and bool(band[1, 3, 9]) and bool(band[1, 4, 9])


def test_a_frame_without_content_has_no_band():
    images = torch.full((2, 5, 5, 3), 255, dtype=torch.uint8)
    assert silhouette_pixels(images, WHITE, 2).numel() == 0


def test_the_sampler_draws_its_share_from_the_band(surface_scene):
    band = silhouette_pixels(surface_scene.images, surface_scene.background, 2)
    h, w = surface_scene.intrinsics.height, surface_scene.intrinsics.width
    sampler = RayBatchSampler(surface_scene, torch.device("cpu"), torch.Generator().manual_seed(3))
    sampler.set_silhouette_band(band, 0.25)
    batch = sampler.sample(400)
    flat = batch.frame * h * w + batch.py * w + batch.px
    in_band = torch.isin(flat, band)
    assert bool(in_band[-100:].all())  # the last round(0.25 * 400) rays are the band's
    # The uniform part lands in the band only as often as the band covers the image, far less.
    assert float(in_band[:-100].float().mean()) < 0.5
    # Their colours are the images' at those pixels, as for every ray.
    expected = surface_scene.images[batch.frame, batch.py, batch.px].float() / 255.0
    assert torch.equal(batch.rgb, expected)


def test_without_a_share_the_draws_are_the_plain_samplers(surface_scene):
    band = silhouette_pixels(surface_scene.images, surface_scene.background, 2)
    plain = RayBatchSampler(surface_scene, torch.device("cpu"), torch.Generator().manual_seed(5))
    off = RayBatchSampler(surface_scene, torch.device("cpu"), torch.Generator().manual_seed(5))
    off.set_silhouette_band(band, 0.0)
    a, b = plain.sample(256), off.sample(256)
    assert torch.equal(a.frame, b.frame) and torch.equal(a.px, b.px) and torch.equal(a.py, b.py)


def test_bad_shares_are_refused(surface_scene):
    sampler = RayBatchSampler(surface_scene, torch.device("cpu"), torch.Generator())
    with pytest.raises(ValueError, match="silhouette share"):
        sampler.set_silhouette_band(torch.arange(4), 1.0)
    for bad in (-0.1, 1.0):
        with pytest.raises(ValueError, match="silhouette_ray_fraction"):
            TrainConfig(silhouette_ray_fraction=bad)


def test_the_trainer_sets_the_band_from_its_configuration(surface_scene):
    recipe = choose_recipe(surface_scene, TrainConfig(iterations=2, resolution_init=24), FieldConfig(hidden_width=16))
    for share in (0.0, 0.3):
        cfg = dataclasses.replace(recipe.train, silhouette_ray_fraction=share)
        trainer = Trainer(surface_scene, None, cfg, torch.device("cpu"), field_cfg=recipe.field, carved=recipe.carved)
        assert trainer.sampler.band_fraction == share
        assert (trainer.sampler.band is None) == (share == 0.0)
        trainer.train_step()  # a step with band rays runs
