"""The inference grid training leaves behind holds only cells that training kept sampling."""

import torch

from visnerf.config import TrainConfig
from visnerf.rendering.occupancy import dilate
from visnerf.testing import make_noise_scene, make_tiny_field
from visnerf.training.trainer import Trainer


def _trainer() -> Trainer:
    field, _ = make_tiny_field([("t", [0.0, 1.0])], seed=1, resolution=12)  # density nearly everywhere
    cfg = TrainConfig(iterations=1, resolution_init=12, resolution_final=12, carve=False, occupancy_resolution=8)
    return Trainer(make_noise_scene(), None, cfg, torch.device("cpu"), init_field=field)


def _ball(res: int = 8) -> torch.Tensor:
    c = (torch.arange(res) + 0.5) / res - 0.5
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    return (x**2 + y**2 + z**2).sqrt() < 0.3


def test_cells_training_stopped_sampling_stay_out_of_the_inference_grid() -> None:
    trainer = _trainer()
    density_alone = trainer.density_occupancy((8, 8, 8))
    assert (density_alone & ~_ball()).any()  # the field has density outside the sampled ball
    trainer.field.set_occupancy(_ball())
    trainer.finish_occupancy()
    grid = trainer.field.occupancy
    assert grid is not None and grid.shape == (8, 8, 8)
    assert not (grid & ~_ball()).any()
    # Only the ball's cells are evaluated: the grid is their density's occupancy (dilated within
    # the ball), which can only lose cells against the whole density's.
    assert torch.equal(grid, trainer.density_occupancy((8, 8, 8), within=_ball()) & _ball())
    assert not (grid & ~(density_alone & _ball())).any()


def test_refining_evaluates_only_the_trained_cells(monkeypatch) -> None:
    """The rebuild evaluates the density in the trained grid's cells only: cells outside it cannot
    join, and a dense cell outside it does not keep its trained neighbour through the dilation."""
    import visnerf.training.occupancy_policy as trainer_module

    seen = []
    real = trainer_module.build_occupancy

    def spy(*args, **kwargs):
        seen.append(args[5] if len(args) > 5 else kwargs.get("candidates"))
        return real(*args, **kwargs)

    monkeypatch.setattr(trainer_module, "build_occupancy", spy)
    trainer = _trainer()
    trainer.field.set_occupancy(_ball())
    trainer.refine_occupancy()
    assert len(seen) == 1 and seen[0] is not None and torch.equal(seen[0], _ball())


def test_without_a_training_grid_the_inference_grid_is_the_densitys() -> None:
    trainer = _trainer()
    assert trainer.field.occupancy is None
    trainer.finish_occupancy()
    assert torch.equal(trainer.field.occupancy, trainer.density_occupancy((8, 8, 8)))


def test_refine_milestones_shrink_the_grid_within_itself_after_the_occupancy_milestones() -> None:
    field, _ = make_tiny_field([("t", [0.0, 1.0])], seed=1, resolution=12)
    cfg = TrainConfig(iterations=100, resolution_init=12, resolution_final=12, carve=False, occupancy_resolution=8,
                      upsample_at=(), occupancy_at=(0.1,), occupancy_min_iterations=0, occupancy_refine_at=(0.5, 0.7))
    trainer = Trainer(make_noise_scene(), None, cfg, torch.device("cpu"), init_field=field)
    trainer.state.iteration = 60  # past the first refine, before the occupancy milestone ran
    trainer._milestones()
    assert trainer.state.occupancy_done == 1 and trainer.state.refines_done == 1
    trainer.field.set_occupancy(_ball())  # as if training had sampled only the ball since
    density_alone = trainer.density_occupancy((8, 8, 8))
    trainer.state.iteration = 80
    trainer._milestones()
    assert trainer.state.refines_done == 2
    assert torch.equal(trainer.field.occupancy, trainer.density_occupancy((8, 8, 8), within=_ball()) & _ball())
    assert not (trainer.field.occupancy & ~(density_alone & _ball())).any()
    trainer.state.iteration = 99
    trainer._milestones()
    assert trainer.state.refines_done == 2  # each milestone once


def test_milestones_count_as_training_time(monkeypatch) -> None:
    import time

    trainer = _trainer()
    monkeypatch.setattr(trainer, "_milestones", lambda: time.sleep(0.3))
    trainer.run(progress_bar=False)
    assert trainer.state.iteration == 1
    assert trainer.state.train_seconds >= 0.3


def test_a_refine_during_training_lets_content_at_the_edge_take_a_new_ring() -> None:
    """With a ring of ``d`` cells, the grid may take cells within ``d`` of itself where the density
    has grown (a surface pressed against the edge is not cut there), and no farther; the grid the
    run ends with still keeps within the cells training sampled (without a ring, a refine cannot
    grow: ``test_occupancy.test_refined_grids_use_the_configured_dilation``)."""
    field, _ = make_tiny_field([("t", [0.0, 1.0])], seed=1, resolution=12)
    cfg = TrainConfig(iterations=1, resolution_init=12, resolution_final=12, carve=False, occupancy_resolution=8,
                      occupancy_refine_dilation=1)
    trainer = Trainer(make_noise_scene(), None, cfg, torch.device("cpu"), init_field=field)
    density_alone = trainer.density_occupancy((8, 8, 8), dilation=0)
    reach = dilate(_ball(), 1)
    assert (density_alone & reach & ~_ball()).any()  # dense cells next to the ball, outside it
    assert (density_alone & ~dilate(reach, 1)).any()  # and dense cells farther out
    trainer.field.set_occupancy(_ball())
    trainer.refine_occupancy()
    grown = trainer.field.occupancy
    assert torch.equal(grown, trainer.density_occupancy((8, 8, 8), within=reach, dilation=1) & reach)
    assert (grown & ~_ball()).any() and not (grown & ~reach).any()
    trainer.field.set_occupancy(_ball())
    trainer.finish_occupancy()
    assert not (trainer.field.occupancy & ~_ball()).any()

