"""A frame rendered in blocks of image rows (``renderer.BLOCK_RAYS``): the same frame as in one
block, each block walked and marched before the next block's rays are made, and the rows of
``image_rays`` those of the whole image."""

import math

import pytest
import torch

from visnerf.data.cameras import Intrinsics, image_rays, orbit_c2w
from visnerf.rendering import renderer
from visnerf.rendering.render_settings import RenderSettings
from visnerf.rendering.renderer import render_image
from visnerf.testing import make_tiny_field


def _scene() -> tuple[torch.nn.Module, torch.Tensor, Intrinsics]:
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=3, resolution=12)
    field.eval()
    c2w = torch.from_numpy(orbit_c2w(35.0, 20.0, 2.2)).float()
    return field, c2w, Intrinsics.from_fov(40, 29, math.radians(40.0))


@pytest.mark.parametrize("threaded", [True, False])
def test_a_frame_in_blocks_of_rows_is_the_frame_in_one_block(two_threads, monkeypatch, threaded: bool) -> None:
    field, c2w, intr = _scene()
    settings = RenderSettings(chunk_rays=64)
    torch.set_num_threads(2 if threaded else 1)
    params = torch.tensor([0.4])
    with torch.inference_mode():
        whole = render_image(field, c2w, intr, params, settings)  # 1160 rays: one block
        monkeypatch.setattr(renderer, "BLOCK_RAYS", 7 * 40 + 13)  # blocks of 7 rows, the last of 1
        blocks = render_image(field, c2w, intr, params, settings)
        monkeypatch.setattr(renderer, "BLOCK_RAYS", 10)  # fewer rays than a row: a row a block
        rows = render_image(field, c2w, intr, params, settings)
    assert whole.shape == (29, 40, 3)
    assert float((whole - torch.tensor(settings.background)).abs().max()) > 0.1  # the frame shows content
    # the same samples and sums; the decoders' products see other batch shapes, which may round the
    # last bit differently (a float32 ulp here; the bundled scenes' 8-bit 1440x1440 frames were equal)
    torch.testing.assert_close(blocks, whole, rtol=0.0, atol=1e-6)
    torch.testing.assert_close(rows, whole, rtol=0.0, atol=1e-6)


def test_each_block_is_marched_before_the_next_blocks_rays_are_made(monkeypatch) -> None:
    field, c2w, intr = _scene()
    events: list[tuple[str, int]] = []
    make, walk = renderer.image_rays, renderer.ray_windows

    def made(c2w, intrinsics, rows):
        events.append(("rays", rows[1] - rows[0]))
        return make(c2w, intrinsics, rows)

    def walked(field, rays_o, *args, **kwargs):
        events.append(("walk", rays_o.shape[0]))
        return walk(field, rays_o, *args, **kwargs)

    monkeypatch.setattr(renderer, "image_rays", made)
    monkeypatch.setattr(renderer, "ray_windows", walked)
    monkeypatch.setattr(renderer, "BLOCK_RAYS", 10 * 40)
    with torch.inference_mode():
        render_image(field, c2w, intr, torch.tensor([0.4]), RenderSettings(chunk_rays=64))
    # each block's rays are walked, chunk by chunk (64 rays at most), before the next block's are made
    blocks: list[list[int]] = []
    for kind, count in events:
        if kind == "rays":
            blocks.append([count * 40])
        else:
            blocks[-1].append(count)
    assert [b[0] for b in blocks] == [400, 400, 360]
    assert all(sum(b[1:]) == b[0] and max(b[1:]) <= 64 for b in blocks)


def test_image_rays_of_some_rows_are_those_rows_of_the_image() -> None:
    _, c2w, intr = _scene()
    all_o, all_d = image_rays(c2w, intr)
    some_o, some_d = image_rays(c2w, intr, (5, 12))
    assert some_d.shape == (7, 40, 3)
    assert torch.equal(some_o, all_o[5:12])
    assert torch.equal(some_d, all_d[5:12])
    for rows in ((0, 0), (-1, 3), (20, 30), (7, 5)):
        with pytest.raises(ValueError, match="not within the image's 29 rows"):
            image_rays(c2w, intr, rows)
