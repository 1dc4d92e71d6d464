"""The weighted row sums VM lookups are made of (``vm_taps.weighted_row_sum``): value and table
gradient against ``embedding_bag``'s own, and an independent scatter in float64."""

import pytest
import torch
import torch.nn.functional as F

from visnerf.representation.vm_taps import transposed_taps, weighted_row_sum


def _case(n_rows: int, channels: int, bags: int, taps: int, dtype: torch.dtype, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    table = torch.randn(n_rows, channels, generator=g, dtype=dtype)
    rows = torch.randint(0, n_rows, (bags, taps), generator=g, dtype=torch.int32)
    rows[: min(bags, 3)] = 0  # repeated rows within and across bags
    weights = torch.rand(bags, taps, generator=g, dtype=dtype)
    cotangent = torch.randn(bags, channels, generator=g, dtype=dtype)
    return table, rows, weights, cotangent


@pytest.mark.parametrize("taps", [4, 2])
def test_value_and_gradient_equal_an_explicit_scatter(taps: int) -> None:
    table, rows, weights, cot = _case(37, 5, 300, taps, torch.float64)
    table.requires_grad_(True)
    out = weighted_row_sum(rows, weights, table)
    expected = (weights[..., None] * table.detach()[rows.long()]).sum(1)
    assert torch.allclose(out, expected, atol=1e-12)
    (grad,) = torch.autograd.grad(out, table, cot)
    slow = torch.zeros_like(table)
    for i in range(rows.shape[0]):
        for k in range(taps):
            slow[rows[i, k]] += weights[i, k] * cot[i]
    assert torch.allclose(grad, slow, atol=1e-12)


def test_gradient_equals_embedding_bag_in_float32_and_accumulates() -> None:
    """Two lookups into one table (two micro-batches) accumulate like embedding_bag's gradients."""
    table, rows, weights, cot = _case(500, 16, 4000, 4, torch.float32)
    mine, ref = table.clone().requires_grad_(True), table.clone().requires_grad_(True)
    for half in (slice(0, 2000), slice(2000, 4000)):
        weighted_row_sum(rows[half], weights[half], mine).backward(cot[half])
        F.embedding_bag(rows[half], ref, per_sample_weights=weights[half], mode="sum").backward(cot[half])
    assert torch.allclose(mine.grad, ref.grad, atol=1e-5, rtol=1e-5)


def test_gradient_is_deterministic_and_independent_of_threads() -> None:
    table, rows, weights, cot = _case(2000, 48, 20000, 4, torch.float32, seed=1)
    table.requires_grad_(True)
    before = torch.get_num_threads()
    grads = []
    try:
        for threads in (1, 2, 2):
            torch.set_num_threads(threads)
            grads.append(torch.autograd.grad(weighted_row_sum(rows, weights, table), table, cot)[0])
    finally:
        torch.set_num_threads(before)
    assert torch.equal(grads[0], grads[1]) and torch.equal(grads[1], grads[2])


def test_no_bags_give_a_zero_gradient() -> None:
    table = torch.randn(10, 3, requires_grad=True)
    out = weighted_row_sum(torch.zeros(0, 4, dtype=torch.int32), torch.zeros(0, 4), table)
    assert out.shape == (0, 3)
    (grad,) = torch.autograd.grad(out, table, torch.zeros(0, 3))
    assert torch.equal(grad, torch.zeros_like(table))


def test_transposed_taps_list_each_rows_readers_in_sample_order() -> None:
    rows = torch.tensor([[2, 0], [2, 2], [1, 0]], dtype=torch.int32)
    weights = torch.tensor([[0.5, 0.25], [1.0, 2.0], [3.0, 4.0]])
    t = transposed_taps(rows, weights, 4)
    assert t.crow_indices().tolist() == [0, 2, 3, 6, 6]  # rows 0, 1, 2 are read 2, 1, 3 times; row 3 never
    assert t.col_indices().tolist() == [0, 2, 2, 0, 1, 1]
    assert t.values().tolist() == [0.25, 4.0, 3.0, 0.5, 1.0, 2.0]
    dense = torch.zeros(4, 3)
    for i in range(3):
        for k in range(2):
            dense[rows[i, k], i] += weights[i, k]
    assert torch.equal(t.to_dense(), dense)
