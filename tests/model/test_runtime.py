"""Process-wide thread settings."""

import pytest
import torch

from visnerf import runtime
from visnerf.runtime import pick_device


@pytest.fixture
def restore_threads(monkeypatch):
    monkeypatch.setattr(runtime, "_explicit_threads", None)
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_an_explicit_thread_count_survives_pick_device(restore_threads, monkeypatch) -> None:
    monkeypatch.setattr(runtime, "default_threads", lambda: 2)
    runtime.configure(1)
    pick_device("cpu")  # calls configure() without a count
    assert torch.get_num_threads() == 1


def test_without_an_explicit_count_the_default_is_used(restore_threads, monkeypatch) -> None:
    monkeypatch.setattr(runtime, "default_threads", lambda: 2)
    torch.set_num_threads(1)
    runtime.configure()
    assert torch.get_num_threads() == 2


def test_a_thread_count_below_one_is_rejected(restore_threads) -> None:
    with pytest.raises(ValueError, match="at least 1"):
        runtime.configure(0)


def test_keep_freed_blocks_applies_both_settings() -> None:
    """glibc's mallopt returns 0 for a value it cannot apply (a mmap threshold above 32 MiB, for
    one), so True means both settings took effect."""
    import sys

    if not sys.platform.startswith("linux"):
        pytest.skip("glibc only")
    assert runtime.keep_freed_blocks()
    assert runtime.KEEP_BLOCKS_BELOW <= 32 << 20
