"""Process-wide thread settings."""

import pytest
import torch

from visnerf import runtime
from visnerf.commands import pick_device


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
