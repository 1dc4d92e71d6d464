"""Large frames give their memory back (``heap``): malloc_trim returns freed heap pages to the
system, and the frame renderer asks for it after large frames only."""

import os
import platform

import numpy as np
import pytest

from visnerf_server import heap


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="malloc_trim is glibc's")
def test_trimming_returns_the_free_pages_of_a_fragmented_heap() -> None:
    blocks = [np.ones(100_000 // 8) for _ in range(2000)]  # 200 MB in blocks below the mmap threshold
    kept = blocks[::10]  # one block in ten stays: the heap's top cannot shrink past them
    del blocks
    before = _rss_mb()
    assert heap.release_free_memory()  # the model's runtime.release_free_memory
    after = _rss_mb()
    assert before - after > 100.0, f"RSS {before:.0f} MB -> {after:.0f} MB"
    assert len(kept) == 200


def test_only_large_frames_trim(monkeypatch) -> None:  # noqa: ANN001
    calls: list[int] = []
    monkeypatch.setattr(heap, "release_free_memory", lambda: calls.append(1) or True)
    heap.after_frame(256 * 256)
    assert calls == []
    heap.after_frame(heap.TRIM_AFTER_PIXELS)
    heap.after_frame(1440 * 1440)
    assert len(calls) == 2


def test_the_frame_renderer_hands_each_frame_size_to_the_heap(client, monkeypatch) -> None:  # noqa: ANN001
    sizes: list[int] = []
    monkeypatch.setattr(heap, "after_frame", sizes.append)
    for width, height in ((40, 30), (64, 64)):
        response = client.get("/api/scenes/tiny/render", params={"width": width, "height": height})
        assert response.status_code == 200
    assert sizes == [1200, 4096]


def test_a_frame_that_stops_early_gives_its_memory_back_too(client, monkeypatch) -> None:  # noqa: ANN001
    from visnerf.inference import RenderCancelled, SceneRenderer

    def cancelled(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202 - as a render stopped at its deadline
        raise RenderCancelled("deadline passed")

    sizes: list[int] = []
    monkeypatch.setattr(heap, "after_frame", sizes.append)
    monkeypatch.setattr(SceneRenderer, "render", cancelled)
    response = client.get("/api/scenes/tiny/render", params={"width": 48, "height": 40})
    assert response.status_code != 200
    assert sizes == [48 * 40]
