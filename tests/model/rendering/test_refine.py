"""Frames marched on a lattice and refined where cells differ (``rendering.refine``): against closed
forms (a bilinear image is blended exactly; a straight edge always marks the cells it crosses),
the spacing rule, and a real field's frame against every pixel marched."""

import math
from dataclasses import replace

import pytest
import torch

from visnerf.config import FramesConfig, RenderConfig
from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.rendering.refine import lattice, refine_frame, refinement_spacing
from visnerf.rendering.render_settings import RenderSettings
from visnerf.rendering.renderer import render_image, render_image_scaled, render_pixels
from visnerf.testing import make_tiny_field

CPU = torch.device("cpu")


class Recorder:
    """A pixel renderer from a closed form that counts the pixels it is asked for."""

    def __init__(self, image) -> None:
        self.image = image
        self.asked: list[torch.Tensor] = []

    def __call__(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        self.asked.append(v * 10_000 + u)
        return self.image(u.to(torch.float64), v.to(torch.float64))

    def pixels(self) -> torch.Tensor:
        return torch.cat(self.asked)


def bilinear(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return torch.stack([0.1 + 0.002 * u, 0.2 + 0.003 * v, 0.05 + 1e-5 * u * v], dim=-1)


def edge(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """A gentle gradient with a step of 0.5 across the line 3u + 2v = 100."""
    step = (3.0 * u + 2.0 * v > 100.0).to(u.dtype)[:, None]
    return bilinear(u, v) * 0.2 + 0.5 * step


def full_image(image, height: int, width: int) -> torch.Tensor:
    vv, uu = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    return image(uu.reshape(-1).double(), vv.reshape(-1).double()).reshape(height, width, 3)


@pytest.mark.parametrize("size, spacing, expected", [(9, 4, [0, 4, 8]), (10, 4, [0, 4, 8, 9]), (5, 2, [0, 2, 4]),
                                                     (6, 2, [0, 2, 4, 5]), (3, 1, [0, 1, 2])])
def test_lattice_ends_on_the_last_pixel(size, spacing, expected) -> None:
    assert lattice(size, spacing, CPU).tolist() == expected


@pytest.mark.parametrize("height, width, spacing", [(37, 50, 4), (64, 64, 2), (33, 17, 4)])
def test_a_bilinear_image_is_blended_exactly_from_its_lattice(height, width, spacing) -> None:
    recorder = Recorder(bilinear)
    out = refine_frame(recorder, height, width, spacing, spread=1.0, device=CPU, dtype=torch.float64)
    torch.testing.assert_close(out, full_image(bilinear, height, width), rtol=0, atol=1e-12)
    rows, cols = lattice(height, spacing, CPU), lattice(width, spacing, CPU)
    assert recorder.pixels().numel() == rows.numel() * cols.numel()  # nothing beyond the first lattice


@pytest.mark.parametrize("spacing", [2, 4, 8])
def test_a_straight_edge_is_marched_wherever_it_crosses(spacing) -> None:
    """A line through a convex cell leaves corners on both sides, so every cell the edge crosses is
    marked at every level and the frame equals the closed form at every pixel."""
    recorder = Recorder(edge)
    out = refine_frame(recorder, 60, 70, spacing, spread=0.1, device=CPU, dtype=torch.float64)
    torch.testing.assert_close(out, full_image(edge, 60, 70), rtol=0, atol=1e-12)
    asked = recorder.pixels()
    assert asked.unique().numel() == asked.numel()  # no pixel marched twice
    assert asked.numel() < 0.5 * 60 * 70


def test_a_frame_too_small_for_the_spacing_marches_what_it_can() -> None:
    recorder = Recorder(edge)
    out = refine_frame(recorder, 3, 40, 4, spread=0.1, device=CPU, dtype=torch.float64)
    torch.testing.assert_close(out, full_image(edge, 3, 40), rtol=0, atol=1e-12)
    assert recorder.pixels().numel() == 3 * 40  # 3 rows hold no cell of 2 or 4 pixels: every pixel


def _camera(size: int, distance: float) -> tuple[torch.Tensor, Intrinsics]:
    return (torch.tensor(orbit_c2w(30.0, 20.0, distance), dtype=torch.float32),
            Intrinsics.from_fov(size, size, math.radians(40.0)))


def test_spacing_is_the_power_of_two_under_a_voxel_at_the_far_corner() -> None:
    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    c2w, cam = _camera(512, 4.0)
    corners = torch.stack(torch.meshgrid(*(box[:, i] for i in range(3)), indexing="ij"), -1).reshape(8, 3)
    far = float(((corners - c2w[:3, 3]) @ -c2w[:3, 2]).max())
    voxel_px = lambda voxel: voxel * cam.fx / far  # noqa: E731
    for voxel, expected in ((0.01, 1), (0.05, 4), (0.03, 2), (0.2, 4)):
        assert refinement_spacing(box, voxel, c2w, cam, 4) == expected, (voxel, voxel_px(voxel))
    assert refinement_spacing(box, 0.2, c2w, cam, 8) == 8
    inside, _ = _camera(512, 0.5)  # the camera inside the box: some content behind it
    assert refinement_spacing(box, 0.2, inside, cam, 4) == 1
    ortho = Intrinsics.from_view_height(512, 512, 4.0)  # 128 pixels per world unit
    assert refinement_spacing(box, 0.02, c2w, ortho, 4) == 2
    assert refinement_spacing(box, 0.01, c2w, ortho, 4) == 1
    for extreme in (Intrinsics(512, 512, math.inf, math.inf, 256.0, 256.0, orthographic=True),
                    Intrinsics(512, 512, 1e-300, 1e-300, 256.0, 256.0, orthographic=True),
                    Intrinsics(512, 512, math.inf, math.inf, 256.0, 256.0)):
        assert refinement_spacing(box, 0.2, c2w, extreme, 4) == 1


def test_render_pixels_marches_the_rays_of_render_image() -> None:
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=3, resolution=16)
    c2w, cam = _camera(24, 3.0)
    settings = RenderSettings()
    params = torch.tensor([0.3])
    with torch.inference_mode():
        whole = render_image(field, c2w, cam, params, settings)
        v, u = torch.tensor([0, 5, 23, 11]), torch.tensor([7, 0, 23, 12])
        some = render_pixels(field, c2w, cam, params, settings)(u, v)
    torch.testing.assert_close(some, whole[v, u], rtol=0, atol=1e-6)


def test_a_large_frame_is_refined_and_close_to_every_pixel_marched() -> None:
    """A 16-voxel field at 192x192 pixels: a voxel spans several pixels, the lattice is 4 apart,
    and the frame is within 45 dB of the one with every pixel marched."""
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=3, resolution=16)
    c2w, cam = _camera(192, 3.0)
    assert refinement_spacing(field.aabb, field.voxel_size(), c2w, cam, 4) == 4
    settings = RenderSettings.from_config(RenderConfig(), (1.0, 1.0, 1.0), "full", FramesConfig())
    params = torch.tensor([0.3])
    with torch.inference_mode():
        every = render_image(field, c2w, cam, params, settings)
        refined = render_image_scaled(field, c2w, cam, params, settings)
        same = render_image_scaled(field, c2w, cam, params, replace(settings, refine_spacing=1))
    assert settings.refine_spacing == 4
    torch.testing.assert_close(same, every, rtol=0, atol=0)
    mse = float(((refined - every) ** 2).mean())
    assert 0.0 < mse < 10 ** (-45 / 10)


@pytest.mark.parametrize("changes, message", [({"refine_spacing": 3}, "refine_spacing must be 1, 2, 4"),
                                              ({"refine_spread": -0.1}, "refine_spread must be within"),
                                              ({"refine_spread": math.nan}, "refine_spread must be within")])
def test_bad_refinement_settings_are_refused(changes, message) -> None:
    with pytest.raises(ValueError, match=message):
        FramesConfig(**changes)


def test_the_exhaustive_reference_marches_every_pixel() -> None:
    assert RenderSettings.from_config(RenderConfig(), (1.0, 1.0, 1.0), "exhaustive").refine_spacing == 1
