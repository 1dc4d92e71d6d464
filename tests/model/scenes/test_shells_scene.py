"""The nested-shells scene: its compiled march against the vectorised twin, the cell tables' bound,
straight-alpha RGBA images."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.data.datasets import load_dataset
from visnerf.scenes.catalog import get_scene
from visnerf.scenes.fields import ShellsField
from visnerf.scenes.reference_renderer import DvrVolume, MarchConfig, RayOutput, render_image
from visnerf.scenes.shells_kernel import (
    FAR_EXPONENT,
    cell_tables,
    lowest_visible_value,
    render_image_fast,
    serves_volume,
)
from visnerf.scenes.transfer_function import TransferFunction, nested_shells_tf
from visnerf.scenes.writer import DatasetOptions, straight_rgba, write_scene

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # small renders: one thread (conftest)


def _camera(azimuth: float, elevation: float, size: int) -> tuple[torch.Tensor, Intrinsics]:
    c2w = torch.tensor(orbit_c2w(azimuth, elevation, 2.1), dtype=torch.float64)
    return c2w, Intrinsics.from_fov(size, size, math.radians(30.0))


@pytest.mark.parametrize("lit", [True, False])
@pytest.mark.parametrize(("time", "azimuth", "elevation"), [(0.0, 30.0, 20.0), (0.7, -120.0, -50.0)])
def test_compiled_march_equals_the_vectorised_twin(lit: bool, time: float, azimuth: float, elevation: float) -> None:
    """Colour within 4e-4 (the twin stops a ray only at the end of a pass of 32 samples, and takes
    the gradient by central differences where the loop has it in closed form), opacity within
    1.5e-4, on a float64 image with its shells, silhouettes and highlights."""
    volume = DvrVolume(ShellsField(time), nested_shells_tf(), support_radius=0.5, lit=lit)
    c2w, intrinsics = _camera(azimuth, elevation, 40)
    config = MarchConfig(step=1.0 / 512.0)
    assert serves_volume(volume, c2w.device)
    twin = render_image(volume, c2w, intrinsics, config)
    fast = render_image_fast(volume, c2w, intrinsics, config)
    assert fast.rgb.dtype == torch.float64 and (twin.opacity > 0.5).sum() > 20  # the view holds cores
    assert (fast.rgb - twin.rgb).abs().max() < 4e-4
    assert (fast.opacity - twin.opacity).abs().max() < 1.5e-4
    hit = twin.opacity > 0.01
    assert ((fast.depth[hit] - twin.depth[hit]).abs() < 1e-3).all() and torch.isinf(fast.depth[twin.opacity == 0]).all()


def test_other_volumes_take_the_vectorised_march() -> None:
    from visnerf.scenes.fields import VortexField

    volume = DvrVolume(VortexField(), nested_shells_tf(), support_radius=0.5)
    assert not serves_volume(volume, torch.device("cpu"))
    c2w, intrinsics = _camera(10.0, 10.0, 9)
    config = MarchConfig(step=1.0 / 64.0)
    assert torch.equal(render_image_fast(volume, c2w, intrinsics, config).rgb, render_image(volume, c2w, intrinsics, config).rgb)


def _cell_of(points: torch.Tensor, cells: int) -> tuple[torch.Tensor, ...]:
    index = ((points + 0.5) * cells).long().clamp(0, cells - 1)
    return index[:, 0], index[:, 1], index[:, 2]


@pytest.mark.parametrize("time", [0.0, 0.35, 1.0])
def test_cell_tables_never_drop_a_visible_value_or_a_near_blob(time: float) -> None:
    """Wherever the field reaches the transfer function's first peak, its cell has a non-zero
    count; and in every counted cell the blobs left out of its list add under 1e-5 to the sum."""
    field = ShellsField(time)
    lowest = lowest_visible_value(nested_shells_tf())
    count, blobs = cell_tables(field, lowest)
    cells = count.shape[0]
    gen = torch.Generator().manual_seed(3)
    points = (torch.rand(200_000, 3, generator=gen, dtype=torch.float64) - 0.5) * 0.98
    values = field(points)
    ix, iy, iz = _cell_of(points, cells)
    n_near = torch.from_numpy(count.astype(np.int64))[ix, iy, iz]
    visible = values > lowest
    assert visible.sum() > 1000 and (n_near[visible] > 0).all()
    assert (n_near == 0).float().mean() > 0.5  # the bound is not trivial: most of the box is skipped
    centres, inv_r2, height = field.blobs(torch.float64, torch.device("cpu"))
    wave, phase, displacement = field.waves(torch.float64, torch.device("cpu"))
    counted = n_near > 0
    p = points[counted]
    warped = p + torch.sin(p @ wave + phase) @ displacement
    terms = height * torch.exp(-0.5 * (warped[:, None, :] - centres).square().sum(-1) * inv_r2)  # [m, b]
    table = torch.from_numpy(blobs.astype(np.int64))[ix[counted], iy[counted], iz[counted]]  # [m, b]
    keep = torch.arange(terms.shape[1]) < n_near[counted][:, None]  # [m, b] the list's entries
    listed = (torch.nn.functional.one_hot(table, terms.shape[1]) * keep[..., None]).sum(1) > 0  # [m, b]
    assert (terms * ~listed).sum(-1).max() < 1e-5
    assert FAR_EXPONENT >= 14.0


def test_lowest_visible_value_is_where_the_opacity_starts() -> None:
    assert lowest_visible_value(nested_shells_tf()) == pytest.approx(0.27)
    grey = (0.5, 0.5, 0.5)
    assert lowest_visible_value(TransferFunction((0.0, 1.0), (grey, grey), (0.2, 0.2))) == -math.inf
    assert lowest_visible_value(TransferFunction((0.0, 1.0), (grey, grey), (0.0, 0.0))) == math.inf


def test_shells_field_lies_in_the_unit_interval_and_moves_with_time() -> None:
    points = torch.rand(20_000, 3, generator=torch.Generator().manual_seed(1)) - 0.5
    early, late = ShellsField(0.0)(points), ShellsField(1.0)(points)
    for values in (early, late):
        assert torch.isfinite(values).all() and values.min() >= 0.0 and values.max() < 1.0
        assert (values > 0.8).any()  # some blobs reach the opaque core's peak
    assert (early - late).abs().mean() > 0.01


def test_straight_rgba_composites_back_to_the_rendered_colour() -> None:
    """``rgb = alpha * colour + (1 - alpha) * background``; a clear ray has alpha 0 and colour 0."""
    alpha = torch.tensor([0.0, 1e-40, 0.3, 1.0], dtype=torch.float64)
    colour = torch.tensor([[0.0, 0.0, 0.0], [0.2, 0.2, 0.2], [0.1, 0.6, 0.9], [1.0, 0.5, 0.0]], dtype=torch.float64)
    background = (1.0, 1.0, 1.0)
    rgb = alpha[:, None] * colour + (1.0 - alpha[:, None]) * torch.tensor(background, dtype=torch.float64)
    out = straight_rgba(RayOutput(rgb, alpha, torch.zeros(4, dtype=torch.float64)), background)
    assert torch.allclose(out[2:, :3], colour[2:]) and torch.equal(out[:, 3], alpha)
    assert torch.equal(out[0], torch.zeros(4, dtype=torch.float64))
    assert torch.allclose(out[:, 3:] * out[:, :3] + (1.0 - out[:, 3:]), rgb)


@pytest.mark.slow
def test_make_scene_writes_rgba_images_that_load_as_the_rendered_frames(tmp_path: Path) -> None:
    spec = get_scene("shells_static")
    assert (spec.resolution, spec.n_views, spec.rgba) == (800, 20, True)
    write_scene(spec, tmp_path, DatasetOptions(resolution=24, n_views=4, n_test_views=2), progress=False)
    image = np.asarray(Image.open(tmp_path / "train" / "r_1.png"))
    assert image.shape == (24, 24, 4) and image[..., 3].min() == 0 and image[..., 3].max() > 200
    scene = load_dataset(tmp_path, "train")
    direct = render_image_fast(spec.volume_at(()), scene.c2w[1], scene.intrinsics, MarchConfig(step=spec.step))
    loaded = scene.images[1].float() / 255.0  # [h, w, 3] composited on white by the loader
    assert (loaded - direct.rgb.reshape(24, 24, 3).float()).abs().max() < 1.5 / 255.0
