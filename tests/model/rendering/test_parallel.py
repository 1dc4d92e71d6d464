"""Chunks of a frame marched on several threads: the same frame as one thread, the intra-op
thread count restored, the caller's autograd mode in the helpers, and the cores shared between
frames rendered at once."""

import math
import threading
import time

import pytest
import torch

from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.rendering.parallel import busy_threads, map_chunks
from visnerf.rendering.render_settings import RenderSettings
from visnerf.rendering.renderer import render_image
from visnerf.testing import make_tiny_field


def test_threaded_chunks_render_the_same_frame(two_threads) -> None:
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=2, resolution=12)
    field.eval()
    intr = Intrinsics.from_fov(30, 22, math.radians(40.0))
    c2w = torch.from_numpy(orbit_c2w(20.0, 30.0, 2.2)).float()
    threaded = RenderSettings(chunk_rays=64)  # 11 chunks
    with torch.inference_mode():
        a = render_image(field, c2w, intr, torch.tensor([0.3]), threaded)
        torch.set_num_threads(1)  # the chunks one after another on the caller's thread
        b = render_image(field, c2w, intr, torch.tensor([0.3]), threaded)
        torch.set_num_threads(2)
    assert torch.equal(a, b)


def test_workers_run_one_intra_op_thread_in_the_callers_mode_and_the_count_comes_back(two_threads) -> None:
    seen: list[tuple[int, bool, bool, str]] = []
    lock = threading.Lock()

    def chunk(i: int) -> None:
        with lock:
            seen.append((torch.get_num_threads(), torch.is_inference_mode_enabled(), torch.is_grad_enabled(),
                         threading.current_thread().name))

    with torch.inference_mode():
        map_chunks(chunk, 8, workers=2)
    assert len(seen) == 8
    assert {s[:3] for s in seen} == {(1, True, False)}
    caller = threading.current_thread().name
    assert all(s[3] == caller or s[3].startswith("visnerf-chunk") for s in seen)
    assert torch.get_num_threads() == 2
    assert busy_threads() == 0
    seen.clear()
    with torch.no_grad():
        map_chunks(chunk, 3, workers=2)
    assert {s[:3] for s in seen} == {(1, False, False)}


def test_an_error_in_a_chunk_reaches_the_caller_and_the_count_comes_back(two_threads) -> None:
    def chunk(i: int) -> None:
        if i == 3:
            raise ValueError("chunk 3 failed")

    with pytest.raises(ValueError, match="chunk 3 failed"):
        map_chunks(chunk, 6, workers=2)
    assert torch.get_num_threads() == 2
    assert busy_threads() == 0


def test_a_frame_alone_borrows_a_helper_and_a_frame_beside_it_marches_on_its_own_thread(two_threads) -> None:
    """Two cores: frame A, alone, marches on its caller and a helper; frame B, started while A's
    two threads march, gets no helper (every chunk on its caller's thread), and A's chunks are
    not held up by B's."""
    names: dict[str, set[str]] = {"a": set(), "b": set()}
    a_running, b_done = threading.Event(), threading.Event()
    lock = threading.Lock()

    def chunk_a(i: int) -> None:
        with lock:
            names["a"].add(threading.current_thread().name)
        a_running.set()
        assert b_done.wait(5.0)  # A's chunks hold their cores until B has finished

    def chunk_b(i: int) -> None:
        with lock:
            names["b"].add(threading.current_thread().name)

    def frame_b() -> None:
        assert a_running.wait(5.0)
        deadline = time.monotonic() + 5.0
        while True:  # until both of A's threads hold a chunk (the helper may start late)
            with lock:
                if len(names["a"]) == 2:
                    break
            assert time.monotonic() < deadline, "A's helper never took a chunk"
            time.sleep(0.001)
        assert busy_threads() == 2
        map_chunks(chunk_b, 6, workers=2)
        b_done.set()

    other = threading.Thread(target=frame_b, name="frame-b")
    other.start()
    map_chunks(chunk_a, 2, workers=2)
    other.join(5.0)
    assert names["b"] == {"frame-b"}
    assert len(names["a"]) == 2 and threading.current_thread().name in names["a"]
    assert busy_threads() == 0
    assert torch.get_num_threads() == 2
