"""The compiled pass that writes the decoders' input rows (``vm_kernel``) against the slow
references: ``grid_sample`` on the planes (``VMGrid._sample``) and ``encode_position``."""

import math

import pytest
import torch

from visnerf.representation import vm_kernel
from visnerf.representation.decoders import encode_position
from visnerf.representation.vm import VMGrid

pytestmark = pytest.mark.skipif(not vm_kernel.available(torch.device("cpu")), reason="numba is not installed")


def _grid(resolution: tuple[int, int, int], components: int = 5, seed: int = 0) -> VMGrid:
    torch.manual_seed(seed)
    return VMGrid(components, resolution, 0.5)


def _coords(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    coords = torch.rand(n, 3, generator=g) * 2 - 1
    coords[:6] = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [1.0, -1.0, 0.0],
                               [-1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1.0, 1.0, -1.0]])  # nodes and corners
    return coords


def _tables(grid: VMGrid) -> vm_kernel.KernelTables:
    return vm_kernel.KernelTables.of(*grid.row_tables(), grid.resolution)


@pytest.mark.parametrize("resolution", [(12, 12, 12), (7, 2, 11), (2, 9, 3)])
def test_features_equal_grid_sample_on_the_planes(resolution) -> None:
    grid = _grid(resolution)
    coords = _coords(700, 1)
    out = torch.full((700, 15), float("nan"))
    _tables(grid).write_rows(coords, out)
    with torch.no_grad():
        expected = grid._sample(coords)  # [n, 3c], grid_sample and line indexing
    assert torch.allclose(out, expected, atol=5e-6, rtol=1e-5)


def test_outside_the_box_reads_the_border_and_nan_reads_inside_the_tables() -> None:
    grid = _grid((9, 6, 8))
    coords = _coords(300, 2) * 1.7
    out = torch.empty(300, 15)
    _tables(grid).write_rows(coords, out)
    with torch.no_grad():
        expected = grid._sample(coords.clamp(-1.0, 1.0))
    assert torch.allclose(out, expected, atol=5e-6, rtol=1e-5)
    # A NaN coordinate never indexes outside the tables: it reads the border (its features are finite).
    bad = torch.tensor([[float("nan"), 0.2, float("inf")], [-float("inf"), float("nan"), 0.0]])
    out = torch.empty(2, 15)
    _tables(grid).write_rows(bad, out)
    with torch.no_grad():
        border = grid._sample(torch.tensor([[-1.0, 0.2, 1.0], [-1.0, -1.0, 0.0]]))
    assert torch.allclose(out, border, atol=5e-6)


@pytest.mark.parametrize("n_freqs", [0, 1, 2, 4])
def test_position_encoding_follows_the_features(n_freqs) -> None:
    grid = _grid((10, 10, 10), components=4)
    coords = _coords(500, 3)
    out = torch.empty(500, 12 + 3 + 6 * n_freqs)
    _tables(grid).write_rows(coords, out, n_freqs)
    with torch.no_grad():
        assert torch.allclose(out[:, :12], grid._sample(coords), atol=5e-6, rtol=1e-5)
    # Later levels come from the double-angle formulas: one float32 rounding per level (|x| <= 1).
    assert torch.allclose(out[:, 12:], encode_position(coords, n_freqs), atol=1e-6 * 2 ** max(n_freqs, 1), rtol=0)
    assert torch.equal(out[:, 12:15], coords)


def test_bfloat16_rows_are_the_float32_rows_rounded_once() -> None:
    grid = _grid((11, 13, 9), components=6)
    coords = _coords(1000, 4)
    exact = torch.empty(1000, 18 + 15)
    _tables(grid).write_rows(coords, exact, 2)
    # a row slice of a padded decoder input, as FrameField hands it over
    padded = torch.zeros(1024, 18 + 15, dtype=torch.bfloat16)
    _tables(grid).write_rows(coords, padded[:1000], 2)
    assert torch.equal(padded[:1000], exact.to(torch.bfloat16))  # round to nearest even, as torch
    # a NaN coordinate gives NaN encodings, still NaN in bfloat16
    nan_row = torch.zeros(1, 33, dtype=torch.bfloat16)
    _tables(grid).write_rows(torch.tensor([[float("nan"), 0.0, 0.5]]), nan_row, 2)
    assert torch.isnan(nan_row[0, 18]) and torch.isnan(nan_row[0, 21]) and torch.isfinite(nan_row[0, :18]).all()
    assert torch.equal(padded[1000:], torch.zeros(24, 33, dtype=torch.bfloat16))


def test_features_only_leave_the_other_columns_alone() -> None:
    grid = _grid((6, 6, 6), components=3)
    out = torch.full((50, 12), 7.0)
    _tables(grid).write_rows(_coords(50, 5), out)
    assert torch.equal(out[:, 9:], torch.full((50, 3), 7.0))


def test_wrong_shapes_and_types_are_refused_by_name() -> None:
    grid = _grid((6, 6, 6), components=3)
    tables = _tables(grid)
    with pytest.raises(ValueError, match="cannot take"):
        tables.write_rows(torch.zeros(4, 3), torch.empty(5, 9))
    with pytest.raises(ValueError, match="cannot take"):
        tables.write_rows(torch.zeros(4, 3), torch.empty(4, 8))
    with pytest.raises(ValueError, match="cannot take"):
        tables.write_rows(torch.zeros(4, 3, dtype=torch.float64), torch.empty(4, 9))
    with pytest.raises(ValueError, match="cannot take"):
        tables.write_rows(torch.zeros(4, 3), torch.empty(9, 4).t())
    with pytest.raises(ValueError, match="float32 or bfloat16"):
        tables.write_rows(torch.zeros(4, 3), torch.empty(4, 9, dtype=torch.float16))
    with pytest.raises(ValueError, match="do not match resolution"):
        vm_kernel.KernelTables.of(*grid.row_tables(), (6, 6, 7))
    tables.write_rows(torch.zeros(0, 3), torch.empty(0, 9))  # nothing to write


def test_the_tables_follow_the_grid_without_a_copy() -> None:
    grid = _grid((5, 5, 5), components=2)
    tables = _tables(grid)
    with torch.no_grad():
        grid.plane_table.mul_(2.0)
    coords = torch.tensor([[0.1, -0.3, 0.7]])
    out = torch.empty(1, 6)
    tables.write_rows(coords, out)
    with torch.no_grad():
        assert torch.allclose(out, grid._sample(coords), atol=5e-6)
    assert math.isfinite(float(out.sum()))
