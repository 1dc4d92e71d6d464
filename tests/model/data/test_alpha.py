"""Images with transparency keep their alpha (``data.images``), and training composites each ray's
target on a background of its own (``training.ray_batches.over_background``,
``TrainConfig.random_backgrounds``)."""

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from visnerf.config import TrainConfig
from visnerf.data.cameras import orbit_c2w
from visnerf.data.datasets import load_dataset
from visnerf.testing import make_noise_scene
from visnerf.training.ray_batches import RayBatchSampler, over_background
from visnerf.training.trainer import Trainer

SIZE = 8


def _dataset(folder: Path, images: list[np.ndarray], white: bool = True) -> Path:
    (folder / "train").mkdir(parents=True)
    frames = []
    for i, pixels in enumerate(images):
        Image.fromarray(pixels).save(folder / "train" / f"r_{i}.png")
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": orbit_c2w(120.0 * i, 20.0, 2.0).tolist()})
    meta = {"camera_angle_x": math.radians(40.0), "white_background": white, "frames": frames}
    (folder / "transforms_train.json").write_text(json.dumps(meta))
    return folder


def _rgba(seed: int, opaque: bool = False) -> np.ndarray:
    pixels = np.random.default_rng(seed).integers(0, 256, (SIZE, SIZE, 4), dtype=np.uint8)
    if opaque:
        pixels[..., 3] = 255
    return pixels


def _composite(rgba: np.ndarray, background: float) -> np.ndarray:
    """The slow reference: straight alpha over a grey level, per pixel in float64, rounded."""
    f = rgba.astype(np.float64) / 255.0
    return np.clip(np.round((f[..., :3] * f[..., 3:] + background * (1.0 - f[..., 3:])) * 255.0), 0, 255)


def test_rgba_images_keep_their_alpha_and_composite_the_colour(tmp_path: Path) -> None:
    images = [_rgba(0), _rgba(1)]
    scene = load_dataset(_dataset(tmp_path / "d", images, white=False), "train")
    assert scene.alpha is not None and scene.alpha.shape == (2, SIZE, SIZE)
    for i, rgba in enumerate(images):
        assert np.array_equal(scene.alpha[i].numpy(), rgba[..., 3])
        assert np.abs(scene.images[i].numpy().astype(np.float64) - _composite(rgba, 0.0)).max() <= 1


def test_opaque_frames_beside_transparent_ones_are_opaque_and_opaque_images_keep_none(tmp_path: Path) -> None:
    rgb = np.random.default_rng(5).integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8)
    mixed = load_dataset(_dataset(tmp_path / "mixed", [rgb, _rgba(2, opaque=True), _rgba(3)]), "train")
    assert mixed.alpha is not None
    assert bool((mixed.alpha[0] == 255).all()) and bool((mixed.alpha[1] == 255).all())
    assert np.array_equal(mixed.alpha[2].numpy(), _rgba(3)[..., 3])
    opaque = load_dataset(_dataset(tmp_path / "opaque", [_rgba(4, opaque=True), rgb]), "train")
    assert opaque.alpha is None  # all opaque: nothing to learn from, nothing kept
    assert np.array_equal(opaque.images[1].numpy(), rgb)


def test_a_subset_takes_its_frames_alpha(tmp_path: Path) -> None:
    scene = load_dataset(_dataset(tmp_path / "d", [_rgba(0), _rgba(1), _rgba(2)]), "train")
    part = scene.subset(torch.tensor([2, 0]))
    assert part.alpha is not None and torch.equal(part.alpha, scene.alpha[[2, 0]])


def test_over_background_matches_compositing_on_the_new_background() -> None:
    g = torch.Generator().manual_seed(0)
    colour, alpha = torch.rand(50, 3, generator=g, dtype=torch.float64), torch.rand(50, generator=g, dtype=torch.float64)
    old, new = torch.rand(50, 3, generator=g, dtype=torch.float64), torch.rand(50, 3, generator=g, dtype=torch.float64)
    on_old = colour * alpha[:, None] + old * (1 - alpha[:, None])
    expected = colour * alpha[:, None] + new * (1 - alpha[:, None])
    assert torch.allclose(over_background(on_old, alpha, old, new), expected, atol=1e-12)
    assert torch.equal(over_background(on_old, torch.ones(50, dtype=torch.float64), old, new), on_old)


def _alpha_scene(alpha: int | None = None, seed: int = 0):
    """The noise scene with random opacities, or all ``alpha`` (its colours then white where 0)."""
    scene = make_noise_scene(n_views=4, size=16)
    shape = scene.images.shape[:3]
    if alpha is None:
        return dataclasses.replace(scene, alpha=torch.randint(0, 256, shape, generator=torch.Generator().manual_seed(seed),
                                                              dtype=torch.uint8))
    images = scene.images if alpha else torch.full_like(scene.images, 255)
    return dataclasses.replace(scene, images=images, alpha=torch.full(shape, alpha, dtype=torch.uint8))


def test_the_sampler_gives_each_ray_its_pixels_alpha() -> None:
    scene = _alpha_scene()
    batch = RayBatchSampler(scene, torch.device("cpu"), torch.Generator().manual_seed(1)).sample(300)
    assert batch.alpha is not None
    assert torch.equal(batch.alpha, scene.alpha[batch.frame, batch.py, batch.px].float() / 255.0)


CFG = TrainConfig(iterations=10, batch_rays=256, resolution_init=8, resolution_final=8)


def test_a_step_trains_each_ray_over_its_own_background() -> None:
    clear = Trainer(_alpha_scene(alpha=0), None, CFG, torch.device("cpu"))._step_batch()
    assert clear.background.shape == (256, 3) and float(clear.background.std()) > 0.2
    assert 0.0 <= float(clear.background.min()) and float(clear.background.max()) <= 1.0
    assert torch.allclose(clear.target, clear.background)  # a clear pixel shows whatever is behind it
    opaque = Trainer(_alpha_scene(alpha=255), None, CFG, torch.device("cpu"))._step_batch()
    assert float(opaque.background.std()) > 0.2
    scene = _alpha_scene(alpha=255)
    colours = {tuple(c) for c in (scene.images.reshape(-1, 3).float() / 255.0).tolist()}
    assert all(tuple(c) in colours for c in opaque.target.tolist())  # an opaque pixel shows its own colour


def test_without_random_backgrounds_a_step_keeps_the_datasets() -> None:
    scene = _alpha_scene(alpha=0)
    fixed = Trainer(scene, None, dataclasses.replace(CFG, random_backgrounds=False), torch.device("cpu"))._step_batch()
    assert torch.equal(fixed.background, torch.ones(256, 3)) and torch.equal(fixed.target, torch.ones(256, 3))
