"""Large frames give their freed memory back (``inference.TRIM_AFTER_PIXELS``): glibc's malloc_trim
returns freed heap pages to the system (``runtime.release_free_memory``), and a scene's render asks
for it after large frames only, finished or stopped early."""

import os
import platform

import numpy as np
import pytest

from visnerf import inference
from visnerf.data.cameras import orbit_c2w
from visnerf.inference import RenderCancelled, load_scene
from visnerf.runtime import release_free_memory
from visnerf.testing import make_tiny_checkpoint


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="malloc_trim is glibc's")
def test_trimming_returns_the_free_pages_of_a_fragmented_heap() -> None:
    blocks = [np.ones(100_000 // 8) for _ in range(2000)]  # 200 MB in blocks below the mmap threshold
    kept = blocks[::10]  # one block in ten stays: the heap's top cannot shrink past them
    del blocks
    before = _rss_mb()
    assert release_free_memory()
    after = _rss_mb()
    assert before - after > 100.0, f"RSS {before:.0f} MB -> {after:.0f} MB"
    assert len(kept) == 200


@pytest.fixture()
def trims(monkeypatch) -> list[int]:
    """Counts the trims; frames of 100 pixels and more count as large."""
    calls: list[int] = []
    monkeypatch.setattr(inference, "release_free_memory", lambda: calls.append(1) or True)
    monkeypatch.setattr(inference, "TRIM_AFTER_PIXELS", 100)
    return calls


def test_only_large_frames_trim(tmp_path, trims) -> None:
    scene = load_scene(make_tiny_checkpoint(tmp_path / "s.safetensors"))
    c2w = orbit_c2w(20.0, 30.0, 2.2)
    scene.render(c2w, 40.0, 9, 11, {"a": 0.5})
    assert trims == []
    scene.render(c2w, 40.0, 10, 10, {"a": 0.5})
    scene.render(c2w, 40.0, 20, 16, {"a": 0.5}, "preview")
    assert len(trims) == 2


def test_a_frame_stopped_early_trims_too(tmp_path, trims) -> None:
    scene = load_scene(make_tiny_checkpoint(tmp_path / "s.safetensors"))
    with pytest.raises(RenderCancelled):
        scene.render(orbit_c2w(20.0, 30.0, 2.2), 40.0, 32, 32, {"a": 0.5}, cancel=lambda: True)
    assert trims == [1]
