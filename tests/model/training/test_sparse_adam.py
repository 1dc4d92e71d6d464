"""RowSparseAdam: torch's Adam where every row holds a gradient, lazy (per-row counts) where marks
say which do; and the grid priors at marked rows equal the dense priors' gradients there."""

import numpy as np
import pytest
import torch

from visnerf.representation.vm import VMGrid
from visnerf.representation.vm_rows import RowGradients
from visnerf.training.regularizers import add_grid_l1_, add_grid_total_variation_
from visnerf.training.row_priors import add_l1_at_marks, add_total_variation_at_marks
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
    table.grad = torch.zeros(6, 2)
    marks = np.zeros(6, np.uint8)
    opt = RowSparseAdam([table], lr=0.1, betas=(0.9, 0.99))
    opt.set_row_marks(table, marks)
    for step in range(3):
        rows = [0] if step < 2 else [0, 4]
        table.grad[rows] = 1.0
        marks[rows] = 1
        opt.step()
        opt.zero_grad()  # leaves the buffer: it is the step's own to clear
        assert table.grad is not None and float(table.grad.abs().sum()) == 0.0 and int(marks.sum()) == 0
    state = opt.state[table]
    assert state["step"].tolist() == [3.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    # Adam's first step moves a row by lr whatever its gradient (bias-corrected): row 4 took one
    # step of its own, not the third step of the optimizer.
    assert torch.allclose(table[4], torch.full((2,), -0.1), atol=1e-6)
    assert torch.equal(table[1], torch.zeros(2)) and torch.equal(table[5], torch.zeros(2))
    with pytest.raises(ValueError, match="row marks"):
        opt.set_row_marks(table, np.zeros(5, np.uint8))


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
    grads.plane_marks[::3] = 1
    grads.line_marks[1::2] = 1
    if prior == "l1":
        add_l1_at_marks(grid, grads, 0.7)
        add_grid_l1_(dense, 0.7)
    else:
        add_total_variation_at_marks(grid, grads, 0.7)
        add_grid_total_variation_(dense, 0.7)
    for ours, theirs, marks in ((grads.plane, dense.plane_table.grad, grads.plane_marks),
                                (grads.line, dense.line_table.grad, grads.line_marks)):
        marked = torch.from_numpy(marks).bool()
        assert torch.allclose(ours[marked], theirs[marked], rtol=1e-12, atol=1e-15)
        assert float(ours[~marked].abs().sum()) == 0.0
        assert float(theirs[marked].abs().sum()) > 0.0


def test_every_mark_set_gives_the_dense_priors_value() -> None:
    torch.manual_seed(1)
    grid = VMGrid(2, (3, 4, 5), 0.5).double()
    grads = RowGradients.of(grid)
    grads.mark_all()
    assert add_l1_at_marks(grid, grads, 0.3) == pytest.approx(0.3 * float(grid.l1().detach()), rel=1e-12)
    assert add_total_variation_at_marks(grid, grads, 0.3) == pytest.approx(0.3 * float(grid.total_variation().detach()),
                                                                           rel=1e-12)
