"""RowSparseAdam: torch's Adam where every row holds a gradient, lazy (per-row counts) where marks
say which do; and the grid priors at marked rows equal the dense priors' gradients there."""

import numpy as np
import pytest
import torch

from visnerf.representation import table_gradients
from visnerf.representation.table_gradients import RowGradients, TableGradient
from visnerf.representation.vm import VMGrid
from visnerf.representation.vm_rows import GridRows
from visnerf.training import row_priors
from visnerf.training.regularizers import add_grid_l1_, add_grid_total_variation_
from visnerf.training.row_priors import add_l1_at_marks, add_total_variation_at_marks, l1_coefficients
from visnerf.training.sparse_adam import RowSparseAdam


def test_without_marks_it_is_torch_adam() -> None:
    g = torch.Generator().manual_seed(0)
    shapes = [(7, 3), (5,), (), (4, 2, 3)]
    ours = [torch.nn.Parameter(torch.randn(s, generator=g)) for s in shapes]
    theirs = [torch.nn.Parameter(p.detach().clone()) for p in ours]
    a = RowSparseAdam([{"params": ours[:2], "lr": 0.02}, {"params": ours[2:], "lr": 0.003}], betas=(0.9, 0.99))
    b = torch.optim.Adam([{"params": theirs[:2], "lr": 0.02}, {"params": theirs[2:], "lr": 0.003}], betas=(0.9, 0.99))
    for _ in range(20):
        for p, q in zip(ours, theirs, strict=True):
            grad = torch.randn(p.shape, generator=g)
            p.grad, q.grad = grad.clone(), grad.clone()
        a.step()
        b.step()
        a.zero_grad()
        b.zero_grad()
    for p, q in zip(ours, theirs, strict=True):
        assert torch.allclose(p, q, rtol=1e-6, atol=1e-6)


def test_marked_rows_alone_move_each_with_its_own_count() -> None:
    table = torch.nn.Parameter(torch.zeros(6, 2))
    source = TableGradient(table, np.array([0, 6]))
    opt = RowSparseAdam([table], lr=0.1, betas=(0.9, 0.99))
    opt.set_row_source(table, source)
    for step in range(3):
        rows = [0] if step < 2 else [0, 4]
        source.buffer()[rows] = 1.0
        source.marks[rows] = 1
        opt.step()
        opt.zero_grad()  # leaves the buffer: it is the step's own to clear
        assert table.grad is not None and float(table.grad.abs().sum()) == 0.0 and int(source.marks.sum()) == 0
    state = opt.state[table]
    assert state["step"].tolist() == [3.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    # Adam's first step moves a row by lr whatever its gradient (bias-corrected): row 4 took one
    # step of its own, not the third step of the optimizer.
    assert torch.allclose(table[4], torch.full((2,), -0.1), atol=1e-6)
    assert torch.equal(table[1], torch.zeros(2)) and torch.equal(table[5], torch.zeros(2))
    with pytest.raises(ValueError, match="not this parameter"):
        opt.set_row_source(torch.nn.Parameter(torch.zeros(6, 2)), source)


@pytest.mark.parametrize("l1", [0.0, 0.3])
def test_updates_from_pending_taps_equal_updates_from_the_materialized_gradient(l1: float) -> None:
    """One pass over the taps (gradient summed per row, the L1 prior added, the row updated) against
    the taps added into ``.grad``, the prior at the marked rows, then the update of the marked rows."""
    g = torch.Generator().manual_seed(0)
    coords = torch.rand(400, 3, generator=g, dtype=torch.float64) * 1.2 - 0.6
    ray = torch.randint(0, 8, (400,), generator=g)
    q = torch.rand(8, 4, generator=g, dtype=torch.float64)
    weights = torch.randn(400, 3 * 8 + 4 + 9, generator=g, dtype=torch.float64)
    grids = []
    for direct in (True, False):
        torch.manual_seed(3)
        grid = VMGrid(8, (6, 7, 8), 0.5).double()
        grads = RowGradients.of(grid)
        opt = RowSparseAdam(grid.parameters(), lr=0.05, betas=(0.9, 0.99))
        for table in grads.tables():
            opt.set_row_source(table.table, table)
        for _ in range(3):
            (GridRows(grid, grads).rows(coords, ray, q, n_freqs=1) * weights).sum().backward()
            for table in grads.tables():
                table.l1_coefficients = None
            if direct and l1 > 0:
                for table in grads.tables():
                    table.l1_coefficients = l1_coefficients(table, l1)
            elif l1 > 0:
                grads.materialize()
                add_l1_at_marks(grid, grads, l1)
            opt.step()
        grids.append(grid)
    assert torch.allclose(grids[0].plane_table, grids[1].plane_table, rtol=0, atol=1e-13)
    assert torch.allclose(grids[0].line_table, grids[1].line_table, rtol=0, atol=1e-13)


def test_small_tables_taken_sample_by_sample_update_as_the_sorted_gather(monkeypatch: pytest.MonkeyPatch) -> None:
    """Taps added into a row buffer sample by sample (``SCATTER_ROWS``) give the sorted gather's
    update float for float: tables, moments, counts and the L1 prior's value, over steps of two
    micro-batches each, in float32 as training runs."""
    g = torch.Generator().manual_seed(5)
    batches = [(torch.rand(300, 3, generator=g) * 1.8 - 0.9, torch.randint(0, 6, (300,), generator=g)) for _ in range(6)]
    q = torch.rand(6, 4, generator=g)
    weights = torch.randn(300, 3 * 8 + 4 + 9, generator=g)
    results = []
    default_rows = table_gradients.SCATTER_ROWS
    for scatter_rows in (default_rows, 0):
        monkeypatch.setattr(table_gradients, "SCATTER_ROWS", scatter_rows)
        torch.manual_seed(3)
        grid = VMGrid(8, (6, 7, 8), 0.5)
        grads = RowGradients.of(grid)
        opt = RowSparseAdam(grid.parameters(), lr=0.05, betas=(0.9, 0.99))
        for table in grads.tables():
            opt.set_row_source(table.table, table)
            table.l1_coefficients = l1_coefficients(table, 0.2)
        l1_values = []
        for step in range(3):
            for coords, ray in batches[2 * step:2 * step + 2]:  # two backwards, two pending parts a table
                (GridRows(grid, grads).rows(coords, ray, q, n_freqs=1) * weights).sum().backward()
            opt.step()
            l1_values.append([table.l1_value for table in grads.tables()])
        results.append((grid, opt, l1_values))
    (grid_a, opt_a, l1_a), (grid_b, opt_b, l1_b) = results
    assert grid_a.plane_table.shape[0] <= default_rows  # the first run took the new path
    assert torch.equal(grid_a.plane_table, grid_b.plane_table) and torch.equal(grid_a.line_table, grid_b.line_table)
    for pa, pb in ((grid_a.plane_table, grid_b.plane_table), (grid_a.line_table, grid_b.line_table)):
        for key in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(opt_a.state[pa][key], opt_b.state[pb][key])
    assert l1_a == l1_b and all(v > 0 for row in l1_a for v in row)


def test_a_dense_adams_state_goes_on_as_a_count_per_row() -> None:
    p = torch.nn.Parameter(torch.ones(3, 2))
    dense = torch.optim.Adam([p], lr=0.1)
    p.grad = torch.ones(3, 2)
    dense.step()
    ours = RowSparseAdam([p], lr=0.1)
    ours.load_state_dict(dense.state_dict())
    p.grad = torch.ones(3, 2)
    ours.step()
    assert ours.state[p]["step"].tolist() == [2.0, 2.0, 2.0]


@pytest.mark.parametrize("prior", ["l1", "tv"])
def test_grid_priors_at_marked_rows_are_the_dense_priors_there(prior: str) -> None:
    torch.manual_seed(0)
    grid = VMGrid(3, (4, 5, 6), 0.5).double()
    dense = VMGrid(3, (4, 5, 6), 0.5).double()
    dense.load_state_dict(grid.state_dict())
    grads = RowGradients.of(grid)
    grads.plane.marks[::3] = 1
    grads.line.marks[1::2] = 1
    if prior == "l1":
        add_l1_at_marks(grid, grads, 0.7)
        add_grid_l1_(dense, 0.7)
    else:
        add_total_variation_at_marks(grid, grads, 0.7)
        add_grid_total_variation_(dense, 0.7)
    for ours, theirs, marks in ((grads.plane.buffer(), dense.plane_table.grad, grads.plane.marks),
                                (grads.line.buffer(), dense.line_table.grad, grads.line.marks)):
        marked = torch.from_numpy(marks).bool()
        assert torch.allclose(ours[marked], theirs[marked], rtol=1e-12, atol=1e-15)
        assert float(ours[~marked].abs().sum()) == 0.0
        assert float(theirs[marked].abs().sum()) > 0.0


def test_every_mark_set_gives_the_dense_priors_value() -> None:
    torch.manual_seed(1)
    grid = VMGrid(2, (3, 4, 5), 0.5).double()
    grads = RowGradients.of(grid)
    for table in grads.tables():
        table.mark_all()
    assert add_l1_at_marks(grid, grads, 0.3) == pytest.approx(0.3 * float(grid.l1().detach()), rel=1e-12)
    assert add_total_variation_at_marks(grid, grads, 0.3) == pytest.approx(0.3 * float(grid.total_variation().detach()),
                                                                           rel=1e-12)


@pytest.mark.parametrize("prior", [add_l1_at_marks, add_total_variation_at_marks], ids=["l1", "tv"])
def test_grid_priors_at_marks_are_the_same_on_any_thread_count(prior, monkeypatch) -> None:
    torch.manual_seed(2)
    grid = VMGrid(4, (9, 10, 11), 0.5)
    results = []
    before = torch.get_num_threads()
    try:
        for threads, least in ((1, 10**9), (2, 4)):  # one part a table; parts of a few rows on two threads
            torch.set_num_threads(threads)
            monkeypatch.setattr(row_priors, "MIN_ROWS_A_PART", least)
            grads = RowGradients.of(grid)
            grads.plane.marks[::3] = 1
            grads.line.marks[1::2] = 1
            value = prior(grid, grads, 0.7)
            results.append((value, grads.plane.buffer().clone(), grads.line.buffer().clone()))
            grid.plane_table.grad = grid.line_table.grad = None
    finally:
        torch.set_num_threads(before)
    (v1, p1, l1), (v2, p2, l2) = results
    assert v1 == v2 and torch.equal(p1, p2) and torch.equal(l1, l2)
    assert float(p1.abs().sum()) > 0.0


def test_a_small_table_materialized_sample_by_sample_is_the_sorted_gather(monkeypatch: pytest.MonkeyPatch) -> None:
    g = torch.Generator().manual_seed(6)
    batches = [(torch.rand(400, 3, generator=g) * 1.8 - 0.9, torch.randint(0, 5, (400,), generator=g)) for _ in range(2)]
    q = torch.rand(5, 4, generator=g)
    weights = torch.randn(400, 3 * 8 + 4 + 9, generator=g)
    results = []
    for scatter_rows in (table_gradients.SCATTER_ROWS, 0):
        monkeypatch.setattr(table_gradients, "SCATTER_ROWS", scatter_rows)
        torch.manual_seed(4)
        grid = VMGrid(8, (6, 7, 8), 0.5)
        grads = RowGradients.of(grid)
        for coords, ray in batches:  # two backwards: two pending parts a table
            (GridRows(grid, grads).rows(coords, ray, q, n_freqs=1) * weights).sum().backward()
        grads.materialize()
        results.append([(t.buffer().clone(), t.marks.copy()) for t in grads.tables()])
    for (grad_a, marks_a), (grad_b, marks_b) in zip(*results, strict=True):
        assert torch.equal(grad_a, grad_b) and np.array_equal(marks_a, marks_b)
        assert marks_a.sum() > 0 and float(grad_a.abs().sum()) > 0.0
