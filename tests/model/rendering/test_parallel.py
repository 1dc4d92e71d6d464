"""Chunks of a frame marched on several threads: the same frame as one thread, the intra-op
thread count restored, and the caller's autograd mode in the workers."""

import math
import threading
from dataclasses import replace

import pytest
import torch

from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.rendering.parallel import map_chunks
from visnerf.rendering.renderer import RenderSettings, render_image
from visnerf.testing import make_tiny_field


def test_threaded_chunks_render_the_same_frame(two_threads) -> None:
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=2, resolution=12)
    field.eval()
    intr = Intrinsics.from_fov(30, 22, math.radians(40.0))
    c2w = torch.from_numpy(orbit_c2w(20.0, 30.0, 2.2)).float()
    threaded = RenderSettings(chunk_rays=64)  # 11 chunks
    with torch.inference_mode():
        a = render_image(field, c2w, intr, torch.tensor([0.3]), threaded)
        b = render_image(field, c2w, intr, torch.tensor([0.3]), replace(threaded, threaded_chunks=False))
    assert torch.equal(a, b)
    assert torch.get_num_threads() == 2


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
    assert all(s[3].startswith("visnerf-chunk") for s in seen)
    assert torch.get_num_threads() == 2
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
