"""Splitting a compiled loop's work over the threads, and asking for a row's cache lines (``visnerf.compiled``)."""

import re
import threading

import numpy as np
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


def _rows_sum_prefetching(table, rows):  # compiled below
    total = 0.0
    for i in range(rows.shape[0]):
        if i + 2 < rows.shape[0]:
            compiled.prefetch_row(table, rows[i + 2])
        for ch in range(table.shape[1]):
            total += table[rows[i], ch]
    return total


def _rows_sum(table, rows):  # the same loop, asking for nothing
    total = 0.0
    for i in range(rows.shape[0]):
        for ch in range(table.shape[1]):
            total += table[rows[i], ch]
    return total


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("columns", [1, 16, 17, 48])
def test_prefetching_rows_leaves_a_loops_values_as_they_are(dtype, columns) -> None:
    loop = compiled.jit(_rows_sum_prefetching)
    table = np.random.default_rng(0).random((50, columns)).astype(dtype)
    rows = np.array([49, 0, 7, 7, 48, 3, 49], np.int64)  # first and last rows, repeats
    assert loop(table, rows) == pytest.approx(float(table[rows].astype(np.float64).sum()), rel=1e-6)


def test_prefetching_a_row_puts_llvm_prefetch_calls_in_the_compiled_code() -> None:
    loop = compiled.numba.njit(_rows_sum_prefetching)  # not cached: numba inspects only what it compiled
    loop(np.zeros((4, 48), np.float32), np.arange(4))
    (llvm,) = loop.inspect_llvm().values()
    calls = re.findall(r"call void @llvm\.prefetch\.\w+\([^)]*i32 0, i32 3, i32 1\)", llvm)
    assert calls  # read, kept in every level, data (LLVM unrolls the loop: as many call sites as it likes)
    plain = compiled.numba.njit(_rows_sum)
    plain(np.zeros((4, 48), np.float32), np.arange(4))
    assert "llvm.prefetch" not in next(iter(plain.inspect_llvm().values()))
