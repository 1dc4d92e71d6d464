"""Splitting a compiled loop's work over the threads (``visnerf.compiled``)."""

import threading

import pytest
import torch

from visnerf import compiled


@pytest.fixture
def threads():
    before = torch.get_num_threads()
    yield lambda n: torch.set_num_threads(n)
    torch.set_num_threads(before)


@pytest.mark.parametrize(("n_threads", "n", "least", "want"), [
    (1, 100, 10, [(0, 100)]),
    (2, 100, 10, [(0, 50), (50, 100)]),
    (2, 15, 10, [(0, 15)]),  # too few items for two threads of at least 10
    (3, 10, 1, [(0, 3), (3, 6), (6, 10)]),
    (2, 0, 1, [(0, 0)]),
])
def test_run_ranges_covers_the_items_in_order_one_range_a_thread(threads, n_threads, n, least, want) -> None:
    threads(n_threads)
    assert compiled.run_ranges(lambda a, b: (a, b), n, least) == want


def test_run_ranges_runs_the_first_range_on_the_caller_and_the_others_beside_it(threads) -> None:
    threads(2)
    seen: dict[int, int] = {}
    compiled.run_ranges(lambda a, b: seen.setdefault(a, threading.get_ident()), 10, 1)
    assert seen[0] == threading.get_ident()
    assert seen[5] != threading.get_ident()


def test_an_error_in_a_range_reaches_the_caller(threads) -> None:
    threads(2)

    def fail_second(a: int, b: int) -> None:
        if a > 0:
            raise ValueError(f"range {a}:{b}")

    with pytest.raises(ValueError, match="range 5:10"):
        compiled.run_ranges(fail_second, 10, 1)
