"""Occupancy dilation: the grown grid against a closed form, and refined training grids built
with the configured dilation; the union over settings against every cell evaluated at every
setting."""

import dataclasses
import itertools

import pytest
import torch

from visnerf.config import TrainConfig
from visnerf.rendering.occupancy import build_occupancy, cell_centres, cell_offsets, dilate
from visnerf.representation.frame_field import FrameField
from visnerf.runtime import bf16_native
from visnerf.testing import make_noise_scene, make_tiny_field
from visnerf.training.trainer import Trainer


def _ball(res: int = 8, radius: float = 0.3) -> torch.Tensor:
    c = (torch.arange(res) + 0.5) / res - 0.5
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    return (x**2 + y**2 + z**2).sqrt() < radius


def _slow_dilate(grid: torch.Tensor, cells: int) -> torch.Tensor:
    """Reference: a cell is set when some set cell lies within ``cells`` along every axis."""
    out = torch.zeros_like(grid)
    set_cells = grid.nonzero().tolist()
    for x, y, z in itertools.product(*(range(n) for n in grid.shape)):
        out[x, y, z] = any(max(abs(x - a), abs(y - b), abs(z - c)) <= cells for a, b, c in set_cells)
    return out


@pytest.mark.parametrize("cells", [0, 1, 2])
def test_dilation_matches_the_chebyshev_ball_around_each_cell(cells: int) -> None:
    g = torch.Generator().manual_seed(cells)
    grid = torch.rand((7, 6, 5), generator=g) > 0.93
    grid[0, 0, 0] = grid[6, 5, 4] = True  # corners: the cube is clipped at the box
    assert torch.equal(dilate(grid, cells), _slow_dilate(grid, cells))


def test_a_single_cell_grows_into_a_cube_of_side_two_d_plus_one() -> None:
    grid = torch.zeros((9, 9, 9), dtype=torch.bool)
    grid[4, 4, 4] = True
    for cells in range(4):
        grown = dilate(grid, cells)
        assert int(grown.sum()) == (2 * cells + 1) ** 3
        assert grown[4 - cells : 5 + cells, 4 - cells : 5 + cells, 4 - cells : 5 + cells].all()


def test_zero_dilation_returns_a_copy_and_negative_is_refused() -> None:
    grid = torch.zeros((3, 3, 3), dtype=torch.bool)
    same = dilate(grid, 0)
    same[0, 0, 0] = True
    assert not grid.any()
    with pytest.raises(ValueError, match="dilation must be >= 0"):
        dilate(grid, -1)


def test_build_occupancy_dilates_the_thresholded_cells_by_the_asked_cells() -> None:
    field, _ = make_tiny_field([("t", [0.0, 1.0])], seed=3, resolution=12)  # density above 0.01 everywhere
    settings = torch.tensor([[0.0], [1.0]])
    ball = _ball(10, 0.25)  # only these cells are evaluated: the rest count as empty before dilating
    bare = build_occupancy(field, (10, 10, 10), settings, 0.03, 0.01, candidates=ball, dilation=0)
    assert torch.equal(bare, ball)
    for cells in (1, 2):
        grown = build_occupancy(field, (10, 10, 10), settings, 0.03, 0.01, candidates=ball, dilation=cells)
        assert torch.equal(grown, dilate(ball, cells)) and int(grown.sum()) > int(ball.sum())
    assert torch.equal(build_occupancy(field, (10, 10, 10), settings, 0.03, 0.01, candidates=ball), dilate(ball, 1))
    with pytest.raises(ValueError, match="dilation must be >= 0"):
        build_occupancy(field, (10, 10, 10), settings, 0.03, 0.01, dilation=-1)


@pytest.mark.parametrize("cells", [0, 1])
def test_refined_grids_use_the_configured_dilation(cells: int) -> None:
    field, _ = make_tiny_field([("t", [0.0, 1.0])], seed=1, resolution=12)
    cfg = TrainConfig(iterations=1, resolution_init=12, resolution_final=12, carve=False, occupancy_resolution=8,
                      occupancy_refine_dilation=cells)
    trainer = Trainer(make_noise_scene(), None, cfg, torch.device("cpu"), init_field=field)
    # A threshold at which only part of the ball holds content, so that dilating changes the grid.
    trainer.render_cfg = dataclasses.replace(trainer.render_cfg, occupancy_threshold=0.07, step_ratio=1.0)
    trainer.field.set_occupancy(_ball())
    bare = trainer.density_occupancy((8, 8, 8), within=_ball(), dilation=0)
    assert 0 < int(bare.sum()) < int((dilate(bare, 1) & _ball()).sum())
    trainer.refine_occupancy()
    # During training the grid may reach ``cells`` past itself (a ring that grows with the content).
    reach = dilate(_ball(), cells)
    assert torch.equal(trainer.field.occupancy,
                       dilate(trainer.density_occupancy((8, 8, 8), within=reach, dilation=0), cells) & reach)
    trainer.field.set_occupancy(_ball())
    trainer.finish_occupancy()  # the inference grid keeps within the cells training sampled
    assert torch.equal(trainer.field.occupancy, dilate(bare, cells) & _ball())


def test_a_negative_refine_dilation_is_refused() -> None:
    with pytest.raises(ValueError, match="occupancy_refine_dilation"):
        TrainConfig(occupancy_refine_dilation=-1)


def _every_cell_at_every_setting(field, res, settings, step, threshold) -> torch.Tensor:
    """Reference union: each setting's own grid, every cell evaluated, then or-ed together."""
    pts = cell_centres(field.aabb, res).reshape(-1, 1, 3) + cell_offsets(res, field.aabb[1] - field.aabb[0], 2)[None]
    grids = []
    with torch.no_grad():
        for setting in settings:
            q_d, q_a = field.param_features(setting[None])
            frame = FrameField(field, q_d, q_a, torch.bfloat16 if bf16_native(pts.device) else torch.float32)
            sigma = frame.density(pts.reshape(-1, 3)).reshape(pts.shape[0], -1).amax(dim=1)
            grids.append((-torch.expm1(-sigma * step) > threshold).reshape(res))
    return torch.stack(grids)


def test_the_union_skips_cells_found_occupied_and_equals_every_setting_evaluated(monkeypatch) -> None:
    """Later settings evaluate only the cells earlier ones left empty: the grid is the union of
    every setting's own grid all the same, and the density is asked for fewer points."""
    field, _ = make_tiny_field([("t", [0.0, 0.5, 1.0])], seed=5, resolution=12)
    field.eval()
    res, step = (10, 10, 10), 0.03
    settings = torch.tensor([[-1.0], [0.0], [1.0]])
    alphas = _every_cell_at_every_setting(field, res, settings, step, 0.0)  # every cell: alpha > 0
    assert alphas.all()
    # a threshold that leaves each setting part of the box, and differs between settings
    with torch.no_grad():
        q_d, q_a = field.param_features(settings[:1])
        sigma = FrameField(field, q_d, q_a).density(cell_centres(field.aabb, res).reshape(-1, 3))
    threshold = float(torch.quantile(-torch.expm1(-sigma * step), 0.6))
    own = _every_cell_at_every_setting(field, res, settings, step, threshold)  # [3, 10, 10, 10]
    union = own.any(dim=0)
    assert 0 < int(own[0].sum()) < int(union.sum()) < union.numel()  # each setting adds cells: the union is real
    asked: list[int] = []
    real_density = FrameField.density

    def counting(self, points):
        asked.append(points.shape[0])
        return real_density(self, points)

    monkeypatch.setattr(FrameField, "density", counting)
    grid = build_occupancy(field, res, settings, step, threshold, dilation=0)
    assert torch.equal(grid, union)
    every = len(settings) * union.numel() * 8  # 8 sub-cells a cell
    assert sum(asked) == 8 * (union.numel() + int((~own[0]).sum()) + int((~(own[0] | own[1])).sum()))
    assert sum(asked) < every
