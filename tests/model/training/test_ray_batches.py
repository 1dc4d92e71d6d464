"""Random ray batches (``training.ray_batches.RayBatchSampler``): rays that miss the box are redrawn,
and the rays kept are uniform over the pixels whose rays hit it."""

import torch

from visnerf.data.cameras import rays_from_pixels
from visnerf.rendering.aabb import intersect_aabb
from visnerf.training.ray_batches import RayBatchSampler


def _small_box() -> torch.Tensor:
    """A box around the scene's centre that a minority of the pixels' rays hit."""
    return torch.tensor([[-0.15, -0.15, -0.15], [0.15, 0.15, 0.15]])


def _hit_pixels(scene, box: torch.Tensor) -> torch.Tensor:
    """[n_frames, h, w] whether each pixel's ray hits ``box``, every pixel's ray made one by one
    frame (the slow reference)."""
    h, w = scene.intrinsics.height, scene.intrinsics.width
    py, px = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    out = []
    for f in range(scene.n_frames):
        o, d = rays_from_pixels(scene.c2w[f].expand(h * w, 4, 4), scene.intrinsics, px.reshape(-1).float() + 0.5,
                                py.reshape(-1).float() + 0.5)
        out.append(intersect_aabb(o, d, box)[2].view(h, w))
    return torch.stack(out)


def test_rays_that_miss_the_box_are_redrawn(surface_scene) -> None:
    box = _small_box()
    share = float(_hit_pixels(surface_scene, box).float().mean())
    assert 0.02 < share < 0.5  # the box is hit by a minority of the rays: most of a first draw misses
    sampler = RayBatchSampler(surface_scene, torch.device("cpu"), torch.Generator().manual_seed(0))
    sampler.set_aabb(box)
    batch = sampler.sample(500)
    assert bool(intersect_aabb(batch.rays_o, batch.rays_d, box)[2].all())
    # each ray is its pixel's, with that pixel's colour and its frame's parameters
    o, d = rays_from_pixels(surface_scene.c2w[batch.frame], surface_scene.intrinsics, batch.px.float() + 0.5,
                            batch.py.float() + 0.5)
    assert torch.equal(o, batch.rays_o) and torch.equal(d, batch.rays_d)
    assert torch.equal(batch.rgb, surface_scene.images[batch.frame, batch.py, batch.px].float() / 255.0)
    assert torch.equal(batch.params, surface_scene.normalized_params()[batch.frame])


def test_the_rays_kept_are_uniform_over_the_pixels_that_hit(surface_scene) -> None:
    box = _small_box()
    hits = _hit_pixels(surface_scene, box)
    sampler = RayBatchSampler(surface_scene, torch.device("cpu"), torch.Generator().manual_seed(1))
    sampler.set_aabb(box)
    draws = 40
    batches = [sampler.sample(500) for _ in range(draws)]
    frame = torch.cat([b.frame for b in batches])
    py = torch.cat([b.py for b in batches])
    h = surface_scene.intrinsics.height
    # each frame's share, and the share in each frame's upper half, against the hit pixels' own
    for kept, counted in ((torch.bincount(frame, minlength=surface_scene.n_frames), hits.sum(dim=(1, 2))),
                          (torch.bincount(frame[py < h // 2], minlength=surface_scene.n_frames),
                           hits[:, : h // 2].sum(dim=(1, 2)))):
        n = frame.numel()
        expected = counted.double() / float(hits.sum()) * n
        sigma = (expected * (1 - expected / n)).sqrt().clamp_min(1.0)
        assert bool(((kept.double() - expected).abs() <= 4 * sigma).all()), (kept, expected)


def test_a_box_no_ray_hits_keeps_the_batch_size(surface_scene) -> None:
    sampler = RayBatchSampler(surface_scene, torch.device("cpu"), torch.Generator().manual_seed(2))
    sampler.set_aabb(torch.tensor([[50.0, 50.0, 50.0], [51.0, 51.0, 51.0]]))
    batch = sampler.sample(64)
    assert batch.rays_o.shape == (64, 3) and not bool(intersect_aabb(batch.rays_o, batch.rays_d,
                                                                       sampler.aabb)[2].any())
