"""The fused step's decoder rows (``vm_rows``) against their slow twin: ``VMGrid.sample`` (grid_sample
and indexing), ``field.modulate``, the parameter features gathered per sample, the positional
encoding and the ray's own columns; values and gradients in float64."""

import numpy as np
import pytest
import torch

from visnerf.representation import vm_rows_kernel
from visnerf.representation.decoders import encode_position
from visnerf.representation.field import modulate
from visnerf.representation.table_gradients import RowGradients
from visnerf.representation.vm import VMGrid
from visnerf.representation.vm_rows import GridRows


def twin_rows(grid: VMGrid, coords, ray, q, n_freqs, tail) -> torch.Tensor:
    qs = q[ray]
    parts = [modulate(grid._sample(coords.clamp(-1.0, 1.0)), qs), qs]
    if n_freqs >= 0:
        parts.append(encode_position(coords, n_freqs))
    return torch.cat([*parts, tail[ray]], dim=-1)


@pytest.mark.parametrize(("n_freqs", "n_tail"), [(2, 0), (-1, 16), (0, 3)])
@pytest.mark.parametrize("n_q", [1, 4])
def test_rows_and_their_gradients_equal_the_twins(n_freqs: int, n_tail: int, n_q: int) -> None:
    g = torch.Generator().manual_seed(0)
    grid = VMGrid(8, (5, 6, 7), 0.5).double()
    twin = VMGrid(8, (5, 6, 7), 0.5).double()
    twin.load_state_dict(grid.state_dict())
    n, m = 6, 300
    coords = torch.rand(m, 3, generator=g, dtype=torch.float64) * 2.4 - 1.2  # some outside: the border
    coords[:4] = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [1.0, -1.0, 0.0], [0.0, 0.0, 0.0]])
    ray = torch.randint(0, n, (m,), generator=g)
    q = torch.rand(n, n_q, generator=g, dtype=torch.float64).requires_grad_(True)
    tail = torch.rand(n, n_tail, generator=g, dtype=torch.float64)
    grads = RowGradients.of(grid)
    rows = GridRows(grid, grads).rows(coords, ray, q, n_freqs, tail)
    q_twin = q.detach().clone().requires_grad_(True)
    expected = twin_rows(twin, coords, ray, q_twin, n_freqs, tail)
    assert rows.shape == expected.shape
    assert torch.allclose(rows, expected, rtol=0, atol=1e-13)
    weights = torch.randn(expected.shape, generator=g, dtype=torch.float64)
    (rows * weights).sum().backward()
    (expected * weights).sum().backward()
    assert grid.plane_table.grad is None  # the tables' gradients wait as taps for the optimizer
    grads.materialize()
    assert torch.allclose(q.grad, q_twin.grad, rtol=0, atol=1e-12)
    assert torch.allclose(grid.plane_table.grad, twin.plane_table.grad, rtol=0, atol=1e-12)
    assert torch.allclose(grid.line_table.grad, twin.line_table.grad, rtol=0, atol=1e-12)


def test_rows_in_float32_stay_within_rounding_and_nan_reads_the_border() -> None:
    g = torch.Generator().manual_seed(1)
    grid = VMGrid(4, (4, 4, 4), 0.5)
    coords = torch.rand(50, 3, generator=g) * 2 - 1
    coords[0, 1] = float("nan")
    ray = torch.zeros(50, dtype=torch.long)
    q = torch.ones(1, 4)
    rows = GridRows(grid).rows(coords, ray, q)
    assert torch.isfinite(rows).all()
    border = coords[:1].clone()
    border[0, 1] = -1.0
    assert torch.allclose(rows[0, :12], grid.sample(border)[0].detach(), atol=1e-6)
    assert torch.allclose(rows[1:, :12], grid.sample(coords[1:]).detach(), atol=1e-6)


def test_the_backward_needs_the_grids_gradients() -> None:
    grid = VMGrid(4, (4, 4, 4), 0.5)
    rows = GridRows(grid).rows(torch.zeros(3, 3), torch.zeros(3, dtype=torch.long), torch.ones(1, 4))
    with pytest.raises(RuntimeError, match="gradients were not set up"):
        rows.sum().backward()


def test_a_table_of_another_type_or_device_is_refused() -> None:
    with pytest.raises(ValueError, match="float32 or float64"):
        GridRows(VMGrid(4, (4, 4, 4), 0.5).half())
    assert np.float64 is GridRows(VMGrid(4, (4, 4, 4), 0.5).double()).float_type


@pytest.mark.parametrize("threads", [1, 2])
def test_the_taps_sorted_by_row_on_any_thread_count_are_a_stable_sort(threads: int, monkeypatch) -> None:
    rng = np.random.default_rng(4)
    m, n_rows = 3001, 97
    corners = np.array([[0, 1, 9, 10], [0, 1, 7, 8], [0, 1, 5, 6]], np.int64)
    rows = rng.integers(0, n_rows - 10, (m, 3))
    weights = rng.random((m, 3, 4), dtype=np.float32)
    monkeypatch.setattr(vm_rows_kernel, "MIN_SAMPLES_A_SORT_PART", 100)  # several parts where threads allow
    starts, taps = np.empty(n_rows + 1, np.int64), np.empty(m * 12, np.int64)
    tap_weights = np.empty(m * 12, np.float32)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(threads)
        vm_rows_kernel.tap_index(rows, weights, corners, n_rows, starts, taps, tap_weights, np.zeros((2, n_rows + 1), np.int64))
    finally:
        torch.set_num_threads(before)
    s, i, k = np.meshgrid(np.arange(m), np.arange(3), np.arange(4), indexing="ij")  # taps in sample order
    row_of = (rows[s, i] + corners[i, k]).ravel()
    order = np.argsort(row_of, kind="stable")
    assert np.array_equal(starts, np.concatenate([[0], np.cumsum(np.bincount(row_of, minlength=n_rows))]))
    assert np.array_equal(taps, (i * m + s).ravel()[order])
    assert np.array_equal(tap_weights, weights[s, i, k].ravel()[order])
