"""VM grids against outer products and their slow twin (grid_sample), in value and gradient."""

import torch

from visnerf.representation.vm import VMGrid


def test_rank_one_vm_equals_outer_product():
    grid = VMGrid(1, (4, 5, 6), 0.1)
    with torch.no_grad():
        for p in grid.planes:
            p.fill_(0.0)
        for line in grid.lines:
            line.fill_(0.0)
        grid.planes[0][0] = torch.arange(20.0).reshape(5, 4)  # XY plane: [y, x]
        grid.lines[0][0] = torch.arange(6.0)  # Z line
    # grid point (x=1, y=2, z=3) in [-1, 1] coordinates
    coords = torch.tensor([[2 * 1 / 3 - 1, 2 * 2 / 4 - 1, 2 * 3 / 5 - 1]])
    feat = grid.sample(coords)
    assert abs(float(feat[0, 0]) - (2 * 4 + 1) * 3.0) < 1e-4
    assert abs(float(grid._sample(coords)[0, 0]) - (2 * 4 + 1) * 3.0) < 1e-4


def test_table_lookup_equals_grid_sample_in_value_and_gradient():
    """``VMGrid.sample`` (row tables, embedding_bag) against its slow twin ``_sample`` (grid_sample,
    indexing), in float64: features and the gradient of every factor for random cotangents, at
    random points, grid nodes, faces and corners."""
    torch.manual_seed(0)
    grid = VMGrid(4, (5, 7, 6), 0.3).double()
    coords = torch.rand(400, 3, dtype=torch.float64) * 2 - 1
    coords[:6] = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [1.0, -1.0, 0.5], [0.5, 0.0, -0.2],
                               [-1.0, 1.0, 1.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    fast, slow = grid.sample(coords), grid._sample(coords)
    assert torch.allclose(fast, slow, atol=1e-12)
    cotangent = torch.randn_like(fast)
    g_fast = torch.autograd.grad(fast, list(grid.parameters()), cotangent)
    g_slow = torch.autograd.grad(slow, list(grid.parameters()), cotangent)
    for a, b in zip(g_fast, g_slow, strict=True):
        assert torch.allclose(a, b, atol=1e-12)
