"""The inference grid training leaves behind holds only cells that training kept sampling."""

import torch

from visnerf.config import TrainConfig
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
    assert torch.equal(grid, density_alone & _ball())


def test_without_a_training_grid_the_inference_grid_is_the_densitys() -> None:
    trainer = _trainer()
    assert trainer.field.occupancy is None
    trainer.finish_occupancy()
    assert torch.equal(trainer.field.occupancy, trainer.density_occupancy((8, 8, 8)))
