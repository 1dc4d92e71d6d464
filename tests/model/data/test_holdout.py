"""Hold-out splits: which frames go to validation, and the training axes they leave."""

import math

import numpy as np
import pytest
import torch

from visnerf.config import HoldoutConfig
from visnerf.data.cameras import Intrinsics
from visnerf.data.holdout import split_holdout
from visnerf.data.scene import SceneData, axes_from_values


def _scene() -> SceneData:
    """Three views at each of the 3 x 3 settings of two axes whose values float32 cannot hold exactly."""
    a_values, b_values = (0.02, 0.11, 0.2), (0.1, 0.45, 0.8)
    settings = [(a, b) for a in a_values for b in b_values]
    values = np.array([s for s in settings for _ in range(3)], dtype=np.float64)  # [27, 2]
    n = values.shape[0]
    _, axes = axes_from_values(["opacity_low", "opacity_high"], values)
    return SceneData(
        images=torch.zeros(n, 4, 4, 3, dtype=torch.uint8),
        c2w=torch.eye(4).expand(n, 4, 4).clone(),
        intrinsics=Intrinsics.from_fov(4, 4, math.radians(30.0)),
        params=torch.from_numpy(values).float(),
        param_axes=axes,
        view_ids=torch.arange(n) % 3,
    )


def test_held_out_views_and_settings_go_to_validation() -> None:
    scene = _scene()
    train, val = split_holdout(scene, HoldoutConfig(views=(1,), settings=((0.11, 0.45),)))
    assert val is not None
    assert train.n_frames + val.n_frames == scene.n_frames
    assert not bool((train.view_ids == 1).any())
    assert not bool(torch.isclose(train.params, torch.tensor([0.11, 0.45])).all(-1).any())
    assert val.n_frames == 9 + 2  # view 1 at every setting, plus the other two views of the held setting


def test_training_axes_keep_the_datasets_exact_values() -> None:
    train, _ = split_holdout(_scene(), HoldoutConfig(views=(0,)))
    low, high = train.param_axes
    assert low.values == (0.02, 0.11, 0.2) and (low.min, low.max, low.default) == (0.02, 0.2, 0.11)
    assert high.values == (0.1, 0.45, 0.8)


def test_holding_out_every_value_but_one_of_an_axis_is_refused() -> None:
    scene = _scene()
    settings = tuple((a, b) for a in (0.02, 0.11) for b in (0.1, 0.45, 0.8))
    with pytest.raises(ValueError, match="single training value"):
        split_holdout(scene, HoldoutConfig(settings=settings))
