"""The carved grid training samples in, grown by ``TrainConfig.carve_dilation`` cells: the box
stays the visual hull's, and the first grid holds the hull and a shell around it."""

import dataclasses

import pytest
import torch

from visnerf.config import FieldConfig, TrainConfig
from visnerf.rendering.occupancy import dilate
from visnerf.training.recipe import choose_recipe
from visnerf.training.trainer import Trainer


def _trainer(scene, dilation: int) -> Trainer:
    recipe = choose_recipe(scene, TrainConfig(iterations=10, resolution_init=24), FieldConfig(hidden_width=16))
    cfg = dataclasses.replace(recipe.train, carve_dilation=dilation)
    return Trainer(scene, None, cfg, torch.device("cpu"), field_cfg=recipe.field, carved=recipe.carved)


def test_the_grid_grows_by_whole_cells_around_the_hull_and_the_box_stays(surface_scene):
    plain, grown = _trainer(surface_scene, 0), _trainer(surface_scene, 2)
    assert torch.equal(plain.field.aabb, grown.field.aabb)
    assert plain.carved is not None and grown.carved is not None
    hull, box = plain.carved
    assert torch.equal(grown.carved[1], box)
    assert torch.equal(grown.carved[0], dilate(hull, 2))
    # The first grid training samples: the hull's cells, and more.
    first_plain, first_grown = plain.field.occupancy, grown.field.occupancy
    assert first_plain is not None and first_grown is not None
    assert bool((first_plain <= first_grown).all()) and int(first_grown.sum()) > int(first_plain.sum())


def test_a_negative_dilation_is_refused():
    with pytest.raises(ValueError, match="carve_dilation"):
        TrainConfig(carve_dilation=-1)
