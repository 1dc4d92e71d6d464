"""Stopping a render between chunks of rays (``rendering.cancel``): a cancel check that turns True
after the first chunk ends the frame there, on one thread or several; the empty-space walk before
the chunks stops between its jumps (or calls); a chunk already running finishes before the caller goes on; a scene render refuses to start once cancelled; occupancy
grid builds handed to a runner that refuses or drops them leave the union grid serving."""

import gc
import math
import threading
import time
from concurrent.futures import Future

import pytest
import torch

from visnerf.config import FramesConfig
from visnerf.data.cameras import Intrinsics, image_rays, orbit_c2w
from visnerf.inference import RenderCancelled, load_scene
from visnerf.rendering import renderer
from visnerf.rendering.parallel import map_chunks
from visnerf.rendering.render_settings import RenderSettings
from visnerf.rendering.renderer import empty_space_of, ray_windows, render_image
from visnerf.rendering.setting_occupancy import SettingOccupancy
from visnerf.testing import make_tiny_checkpoint, make_tiny_field


class CancelAfter:
    """A cancel check that answers False ``allowed`` times, then True; counts the False answers
    (the chunks let through)."""

    def __init__(self, allowed: int) -> None:
        self.allowed = allowed
        self.let_through = 0
        self._lock = threading.Lock()

    def __call__(self) -> bool:
        with self._lock:
            if self.let_through < self.allowed:
                self.let_through += 1
                return False
            return True


@pytest.mark.parametrize("threaded", [True, False])
def test_a_cancelled_render_stops_after_the_chunk_it_was_in(two_threads, monkeypatch, threaded: bool) -> None:
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=2, resolution=12)
    field.eval()
    intr = Intrinsics.from_fov(64, 64, math.radians(40.0))
    c2w = torch.from_numpy(orbit_c2w(20.0, 30.0, 2.2)).float()
    settings = RenderSettings(chunk_rays=128)  # 32 chunks
    params = torch.tensor([0.3])
    torch.set_num_threads(2 if threaded else 1)  # one after another: on one thread, as a worker would
    marched = {"chunks": 0}
    march = renderer.march_rays

    def counted_march(*args, **kwargs):
        marched["chunks"] += 1
        return march(*args, **kwargs)

    monkeypatch.setattr(renderer, "march_rays", counted_march)
    with torch.inference_mode():
        counting = CancelAfter(10**9)  # never cancels; counts the checks of a whole frame
        whole = render_image(field, c2w, intr, params, settings, cancel=counting)
        whole_chunks, marched["chunks"] = marched["chunks"], 0
        before_chunks = counting.let_through - whole_chunks  # the start and the empty-space walk
        cancel = CancelAfter(before_chunks + 1)
        with pytest.raises(RenderCancelled):
            render_image(field, c2w, intr, params, settings, cancel=cancel)
    assert whole.shape == (64, 64, 3)
    assert cancel.let_through == before_chunks + 1
    # chunks counted, not timed (a loaded machine blurs times): the one let through, and on two
    # threads at most the other thread's chunk already past its check
    assert whole_chunks == 32
    assert 1 <= marched["chunks"] <= (2 if threaded else 1), marched


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "torch"])
def test_the_empty_space_walk_stops_between_jumps(compiled: bool, monkeypatch) -> None:
    """The sample windows of a large frame's rays take a while to find, before any chunk: the
    torch walk asks the cancel check between its jumps, the compiled walk between its calls of
    ``RAYS_PER_CALL`` rays, and a check that stays False changes nothing."""
    from visnerf.rendering import empty_space_kernel

    if compiled and not empty_space_kernel.available(torch.device("cpu")):
        pytest.skip("numba is not installed")
    if compiled:
        monkeypatch.setattr(empty_space_kernel, "RAYS_PER_CALL", 256)  # 1200 rays: five calls
    else:
        monkeypatch.setattr(empty_space_kernel, "available", lambda device: False)
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=4, resolution=8)
    field.eval()
    grid = torch.zeros(8, 8, 8, dtype=torch.bool)
    grid[2:6, 1:7, 3:5] = True
    field.set_occupancy(grid)
    rays_o, rays_d = image_rays(torch.from_numpy(orbit_c2w(35.0, 25.0, 2.2)).float(),
                                Intrinsics.from_fov(40, 30, math.radians(40.0)))
    rays_o, rays_d = rays_o.reshape(-1, 3), rays_d.reshape(-1, 3)
    empty, step = empty_space_of(field), field.voxel_size() * 0.5
    with torch.inference_mode():
        plain = ray_windows(field, rays_o, rays_d, step, 1024, empty)
        asked = ray_windows(field, rays_o, rays_d, step, 1024, empty, cancel=lambda: False)
        cancel = CancelAfter(1)
        with pytest.raises(RenderCancelled):
            ray_windows(field, rays_o, rays_d, step, 1024, empty, cancel=cancel)
    assert torch.equal(plain.first, asked.first) and torch.equal(plain.last, asked.last)
    assert cancel.let_through == 1  # stopped at the second jump or call


def test_map_chunks_lets_running_chunks_end_and_skips_the_rest(two_threads) -> None:
    ran: list[int] = []
    finished = threading.Event()

    def chunk(i: int) -> None:
        if i == 0:
            time.sleep(0.05)
            raise RenderCancelled("stop")
        if i == 1:
            time.sleep(0.3)
            finished.set()
        else:
            time.sleep(0.02)
        ran.append(i)

    with pytest.raises(RenderCancelled):
        map_chunks(chunk, 50, workers=2)
    assert finished.is_set()  # chunk 1 was running: it ended before the caller went on
    assert len(ran) < 10  # the chunks not started were skipped


def _held(o: object) -> bool:
    """Whether ``o`` is a cancellation or a future (by its type: ``isinstance`` asks a dead weak
    proxy among the collector's objects for its class, which raises)."""
    return issubclass(type(o), RenderCancelled | Future)


@pytest.mark.parametrize("threaded", [True, False])
def test_a_cancelled_render_leaves_nothing_for_the_garbage_collector(two_threads, threaded: bool) -> None:
    """Once the caller drops the exception, reference counting frees the frame's tensors: no cycle
    through the chunks' futures keeps them (a server's collector runs rarely, and what it frees
    late is not trimmed)."""
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=2, resolution=12)
    field.eval()
    intr = Intrinsics.from_fov(64, 64, math.radians(40.0))
    c2w = torch.from_numpy(orbit_c2w(20.0, 30.0, 2.2)).float()
    settings = RenderSettings(chunk_rays=128)
    torch.set_num_threads(2 if threaded else 1)
    gc.collect()
    gc.disable()
    try:
        earlier = [o for o in gc.get_objects() if _held(o)]  # other tests' (held)
        with torch.inference_mode():
            for allowed in (0, 3, 9):
                with pytest.raises(RenderCancelled):
                    render_image(field, c2w, intr, torch.tensor([0.3]), settings, cancel=CancelAfter(allowed))
        left = [type(o).__name__ for o in gc.get_objects()
                if _held(o) and not any(o is e for e in earlier)]
    finally:
        gc.enable()
    assert left == []


def test_a_scene_render_cancelled_before_it_starts_renders_nothing(tmp_path) -> None:
    scene = load_scene(make_tiny_checkpoint(tmp_path / "s.safetensors"))
    c2w = orbit_c2w(30.0, 20.0, 2.5)
    with pytest.raises(RenderCancelled):
        scene.render(c2w, 30.0, 16, 16, {}, "full", cancel=lambda: True)
    image = scene.render(c2w, 30.0, 16, 16, {}, "full", cancel=lambda: False)
    assert image.shape == (16, 16, 3)


def test_a_due_build_goes_to_its_caller_and_a_drop_or_a_failure_is_harmless() -> None:
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=3, resolution=8)
    field.eval()
    field.set_occupancy(torch.ones(8, 8, 8, dtype=torch.bool))  # a union grid to narrow
    step = field.voxel_size()
    cache = SettingOccupancy(field, FramesConfig(setting_grids=4, setting_grid_after=1), 1e-4)
    a, b = torch.tensor([0.5]), torch.tensor([0.25])
    space, build = cache.lookup(a, step)
    assert space is None and build is not None
    assert cache.lookup(a, step) == (None, None)  # being built: the union serves, no second build
    assert cache.lookup(b, step) == (None, None)  # one build at a time: b asks again later
    build.drop()  # e.g. a render queue that takes no work now
    space, build = cache.lookup(a, step)  # a new build is handed out
    assert space is None and build is not None
    build.run()
    build.drop()  # a drop after the build ended changes nothing
    space, again = cache.lookup(a, step)
    assert space is not None and again is None and cache.builds == 1

    def fail(params, step):
        raise RuntimeError("out of memory")

    cache.build = fail  # type: ignore[method-assign]
    _, build = cache.lookup(b, step)
    assert build is not None
    build.run()  # logged; nothing stored, and the slot is free again
    assert cache.builds == 1 and cache.lookup(b, step)[1] is not None

    # A dropped build is handed out again at the tuple's next ask; a failed one after the usual asks.
    cache = SettingOccupancy(field, FramesConfig(setting_grids=4, setting_grid_after=2), 1e-4)
    assert cache.lookup(a, step) == (None, None)
    _, build = cache.lookup(a, step)
    assert build is not None
    build.drop()
    _, build = cache.lookup(a, step)
    assert build is not None
    cache.build = fail  # type: ignore[method-assign]
    build.run()
    assert cache.lookup(a, step) == (None, None) and cache.lookup(a, step)[1] is not None

