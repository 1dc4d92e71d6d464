"""Occupancy grids per parameter tuple: the cache serves each tuple its own grid and no other,
builds only for tuples asked for again, evicts the least recently used, never holds a cell the
union lacks, and frames marched with it match frames marched with the union."""

import dataclasses
import math

import pytest
import torch

from visnerf.checkpoint import CheckpointMeta, ParamAxis, save_checkpoint
from visnerf.config import FramesConfig, RenderConfig
from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.inference import load_scene
from visnerf.provenance import Provenance
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.occupancy import build_occupancy, parameter_settings
from visnerf.rendering.render_settings import RenderSettings
from visnerf.rendering.renderer import render_image
from visnerf.rendering.setting_occupancy import (
    SettingOccupancy,
    build_setting_grid,
    param_key,
)
from visnerf.testing import make_tiny_field

STEP_RATIO = 1.0


@pytest.fixture()
def field():
    """A tiny field whose visible cells change with the parameter: its raw density scaled by 60
    and shifted by -20, so that at a = 0 half the cells are visible and at a = 1 all (the union)."""
    f, _ = make_tiny_field([("a", [0.0, 0.5, 1.0])], seed=11, resolution=12)
    f.cfg = dataclasses.replace(f.cfg, density_shift=-20.0)
    with torch.no_grad():
        f.density_decoder.out.weight.mul_(60.0)
        f.density_decoder.out.bias.mul_(60.0)
    f = f.eval()
    settings = parameter_settings([f.density_params.knots(0)], 64)
    step = f.voxel_size() * STEP_RATIO
    f.set_occupancy(build_occupancy(f, (12, 12, 12), settings, step, threshold=1e-4))
    return f


def serve(cache: SettingOccupancy, params: torch.Tensor, step: float) -> EmptySpace | None:
    """A frame's lookup, a due build run by the cache itself (as ``SceneRenderer.render`` does)."""
    space, build = cache.lookup(params, step)
    return cache.run_own(build) if build is not None else space


def grid_of(space: EmptySpace) -> torch.Tensor:
    return space.occupied.bool().reshape(space.shape)


def test_each_tuple_gets_its_own_grid_and_no_other(field) -> None:
    step = field.voxel_size() * STEP_RATIO
    cache = SettingOccupancy(field, FramesConfig(setting_grids=4, setting_grid_after=2), 1e-4, background=False)
    a, b = torch.tensor([-1.0]), torch.tensor([1.0])
    own_a, own_b = (build_setting_grid(field, p, step, 1e-4) for p in (a, b))
    assert not torch.equal(own_a, own_b), "the test needs settings whose grids differ"
    assert serve(cache, a, step) is None  # asked once: the union serves
    first = serve(cache, a, step)
    assert first is not None and torch.equal(grid_of(first), own_a)
    assert serve(cache, b, step) is None
    assert torch.equal(grid_of(serve(cache, b, step)), own_b)
    again = serve(cache, a, step)
    assert again is first and torch.equal(grid_of(again), own_a)
    # A tuple that differs by the least amount is another key: not served A's grid.
    nudged = torch.tensor([math.nextafter(-1.0, 0.0)], dtype=torch.float64)
    assert param_key(nudged) != param_key(a)
    assert serve(cache, nudged, step) is None
    assert cache.builds == 2


def test_background_builds_serve_the_union_until_ready_then_their_own_tuple(field) -> None:
    step = field.voxel_size() * STEP_RATIO
    cache = SettingOccupancy(field, FramesConfig(setting_grids=4, setting_grid_after=2), 1e-4)
    a, b = torch.tensor([-1.0]), torch.tensor([1.0])
    assert serve(cache, a, step) is None
    assert serve(cache, a, step) is None  # the build has started; the union serves meanwhile
    assert serve(cache, b, step) is None
    assert serve(cache, b, step) is None  # the worker is busy with a: b waits for a later frame
    cache.wait()
    assert cache.builds == 1
    assert torch.equal(grid_of(serve(cache, a, step)), build_setting_grid(field, a, step, 1e-4))
    assert serve(cache, b, step) is None  # now b's build starts
    cache.wait()
    assert torch.equal(grid_of(serve(cache, b, step)), build_setting_grid(field, b, step, 1e-4))
    assert cache.builds == 2


def test_least_recently_used_grid_is_dropped(field) -> None:
    step = field.voxel_size() * STEP_RATIO
    cache = SettingOccupancy(field, FramesConfig(setting_grids=2, setting_grid_after=1), 1e-4, background=False)
    a, b, c = torch.tensor([-1.0]), torch.tensor([0.0]), torch.tensor([1.0])
    serve(cache, a, step)
    serve(cache, b, step)
    serve(cache, a, step)  # a is now the most recent
    serve(cache, c, step)  # drops b
    assert len(cache) == 2 and cache.builds == 3
    serve(cache, a, step)
    assert cache.builds == 3
    assert torch.equal(grid_of(serve(cache, b, step)), build_setting_grid(field, b, step, 1e-4))
    assert cache.builds == 4


def test_a_setting_grid_is_inside_the_union_and_narrower(field) -> None:
    step = field.voxel_size() * STEP_RATIO
    union = field.occupancy
    counts = []
    for value in (-1.0, -0.3, 0.0, 0.7, 1.0):
        own = build_setting_grid(field, torch.tensor([value]), step, 1e-4)
        assert not bool((own & ~union).any())
        counts.append(int(own.sum()))
    assert min(counts) < 0.6 * int(union.sum())


def test_frames_with_a_setting_grid_match_frames_with_the_union(field) -> None:
    settings = RenderSettings(step_ratio=STEP_RATIO, early_stop_eps=1e-4, weight_threshold_per_voxel=1e-4, first_segment_samples=4)
    intr = Intrinsics.from_fov(32, 32, math.radians(40.0))
    step = field.voxel_size() * STEP_RATIO
    for value, azimuth in ((-1.0, 10.0), (0.4, 75.0), (1.0, -120.0)):
        params = torch.tensor([value])
        c2w = torch.from_numpy(orbit_c2w(azimuth, 25.0, 1.6)).float()
        own = EmptySpace.of(build_setting_grid(field, params, step, 1e-4), field.aabb)
        with torch.inference_mode():
            union_frame = render_image(field, c2w, intr, params, settings)
            own_frame = render_image(field, c2w, intr, params, settings, own)
        assert (union_frame - 1.0).abs().max() > 0.05  # something is in the picture
        assert float((union_frame - own_frame).abs().max()) < 2e-3


def test_cache_off_and_bad_configs() -> None:
    f, _ = make_tiny_field([("a", [0.0, 1.0])], seed=1, resolution=8)
    assert SettingOccupancy(f, FramesConfig(setting_grids=0), 1e-4).lookup(torch.tensor([0.0]), 0.1) == (None, None)
    assert SettingOccupancy(f, FramesConfig(setting_grid_after=1), 1e-4).lookup(torch.tensor([0.0]), 0.1) == (None, None)  # no grid
    with pytest.raises(ValueError, match="setting_grids"):
        FramesConfig(setting_grids=-1)
    with pytest.raises(ValueError, match="setting_grid_after"):
        FramesConfig(setting_grid_after=0)
    with pytest.raises(ValueError, match="must not exceed segment_samples"):
        FramesConfig(segment_samples=32, first_segment_samples=64)
    with pytest.raises(ValueError, match="no occupancy grid"):
        build_setting_grid(f, torch.tensor([0.0]), 0.1, 1e-4)


def test_scene_renderer_builds_once_per_repeated_tuple_and_frames_agree(field, tmp_path) -> None:
    """Through the public inference API, as the server renders: the first full frames at a tuple
    use the union, the ``setting_grid_after``-th starts the build, later ones use the tuple's grid;
    previews never build; the frames agree to within a level of 8 bits."""
    meta = CheckpointMeta(
        field=field.current_config(), render=RenderConfig(step_ratio=0.5), param_axes=(ParamAxis("a", 0.0, 1.0, (0.0, 0.5, 1.0), 0.5),),
        bbox=((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5)), camera={"azimuth": 30.0, "elevation": 20.0, "distance": 1.6, "fov_deg": 40.0},
        image_width=32, image_height=32, title="Tiny", kind="dvr",
        provenance=Provenance(dataset="random"),
    )
    scene = load_scene(save_checkpoint(field, meta, tmp_path / "tiny.safetensors"))
    c2w = orbit_c2w(40.0, 20.0, 1.6)
    for _ in range(3):
        scene.render(c2w, 40.0, 32, 32, {"a": 0.2}, "preview")
    assert scene.setting_occupancy.builds == 0 and len(scene.setting_occupancy._asked) == 0
    frames = []
    for _ in range(FramesConfig().setting_grid_after - 1):
        frames.append(scene.render(c2w, 40.0, 32, 32, {"a": 0.2}, "full"))
        assert scene.setting_occupancy.builds == 0
    frames.append(scene.render(c2w, 40.0, 32, 32, {"a": 0.2}, "full"))
    scene.setting_occupancy.wait()
    assert scene.setting_occupancy.builds == 1
    frames.append(scene.render(c2w, 40.0, 32, 32, {"a": 0.2}, "full"))
    assert len(scene.setting_occupancy) == 1
    assert int(abs(frames[0].astype(int) - 255).max()) > 10  # content in the picture
    assert max(int(abs(f.astype(int) - frames[0].astype(int)).max()) for f in frames) <= 1
