"""Hold-out splits: which frames go to validation, and the training axes they leave."""

import math

import numpy as np
import pytest
import torch

from visnerf.config import HoldoutConfig
from visnerf.data.cameras import Intrinsics
from visnerf.data.holdout import HELD_OUT_KINDS, axis_index, held_out_kind, split_holdout
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


def test_training_frames_sit_exactly_on_their_axes_knots() -> None:
    """Parameters read back from float32 (0.11 is 0.10999999940) normalise exactly where the
    axis's own values do: training reads the field's tables at their knots, nowhere between."""
    scene = _scene()
    params, knots = scene.normalized_params(), scene.knots()
    for k in range(params.shape[1]):
        assert bool(torch.isin(params[:, k], knots[k]).all())
    axis = scene.param_axes[0]
    assert axis.training_value(float(np.float32(0.11))) == 0.11
    assert axis.training_value(0.1101) == 0.1101  # a value between: kept as it is
    assert axis.normalize(float(np.float32(0.2))) == 1.0


def test_holding_out_every_value_but_one_of_an_axis_is_refused() -> None:
    scene = _scene()
    settings = tuple((a, b) for a in (0.02, 0.11) for b in (0.1, 0.45, 0.8))
    with pytest.raises(ValueError, match="single training value"):
        split_holdout(scene, HoldoutConfig(settings=settings))


def test_a_held_out_axis_value_takes_every_frame_at_it() -> None:
    scene = _scene()
    train, val = split_holdout(scene, HoldoutConfig(axis_values=((0, 0.11),)))
    assert val is not None
    assert val.n_frames == 9  # 3 settings x 3 views
    assert torch.allclose(val.params[:, 0], torch.tensor(0.11))
    assert train.n_frames == 18
    assert not bool(torch.isclose(train.params[:, 0], torch.tensor(0.11)).any())
    low, high = train.param_axes
    assert low.values == (0.02, 0.2) and (low.min, low.max) == (0.02, 0.2)  # training keeps the ends
    assert high.values == (0.1, 0.45, 0.8)
    assert val.param_axes == train.param_axes


def test_axis_values_join_views_and_settings() -> None:
    scene = _scene()
    train, val = split_holdout(scene, HoldoutConfig(views=(1,), settings=((0.02, 0.45),), axis_values=((1, 0.8),)))
    assert val is not None
    # view 1 at 9 settings; the other 2 views at (0.02, 0.45); the other 2 views at b = 0.8 (3 settings)
    assert val.n_frames == 9 + 2 + 6
    assert train.n_frames + val.n_frames == scene.n_frames
    assert not bool(torch.isclose(train.params[:, 1], torch.tensor(0.8)).any())


def test_an_axis_value_that_matches_no_frame_holds_nothing_out() -> None:
    scene = _scene()  # as a setting that matches no frame
    train, val = split_holdout(scene, HoldoutConfig(axis_values=((0, 0.15),)))
    assert val is None and train is scene
    train, val = split_holdout(scene, HoldoutConfig(views=(2,), axis_values=((0, 0.15),)))
    assert val is not None and val.n_frames == 9


@pytest.mark.parametrize("axis", [2, 7])
def test_an_axis_the_dataset_lacks_is_named(axis: int) -> None:
    with pytest.raises(ValueError, match=rf"axis {axis} does not exist; this dataset has 2 varying parameters, "
                                         r"axes 0 to 1 \(opacity_low, opacity_high\)"):
        split_holdout(_scene(), HoldoutConfig(axis_values=((axis, 0.11),)))


@pytest.mark.parametrize(
    ("axis_values", "message"),
    [
        (((-1, 0.11),), "the axis must be an index of at least 0, got -1"),
        (((True, 0.11),), "the axis must be an index of at least 0, got True"),
        (((0, math.nan),), "the value must be a finite number, got nan"),
        (((0, math.inf),), "the value must be a finite number, got inf"),
    ],
)
def test_bad_axis_values_are_refused_by_the_config(axis_values, message: str) -> None:
    """(Values of the wrong type, a float axis or a string value, are refused by the type check the
    tests run under before the config sees them; the config's own check refuses them without it.)"""
    with pytest.raises(ValueError, match=message):
        HoldoutConfig(axis_values=axis_values)


def test_holding_out_the_only_other_value_of_an_axis_is_refused() -> None:
    scene = _scene()
    with pytest.raises(ValueError, match="single training value"):
        split_holdout(scene, HoldoutConfig(axis_values=((0, 0.02), (0, 0.2))))


def test_axis_names_and_indices_resolve() -> None:
    scene = _scene()
    assert axis_index(scene, "opacity_high") == 1
    assert axis_index(scene, "0") == 0
    assert axis_index(scene, "5") == 5  # the range is split_holdout's to check, against the same scene
    with pytest.raises(ValueError, match=r"no parameter axis 'OmM': this dataset's varying parameters are "
                                         r"0 'opacity_low', 1 'opacity_high'"):
        axis_index(scene, "OmM")


def test_a_negative_view_is_refused() -> None:
    with pytest.raises(ValueError, match="held-out view -1 must be a whole number of at least 0"):
        HoldoutConfig(views=(-1,))


def test_each_held_out_frame_is_told_why_the_newest_count_first() -> None:
    scene = _scene()
    holdout = HoldoutConfig(views=(1,), settings=((0.02, 0.45),), axis_values=((1, 0.8),))
    kinds = held_out_kind(scene, holdout)
    for i, kind in enumerate(kinds):
        a, b = scene.params[i].tolist()
        if math.isclose(b, 0.8, abs_tol=1e-6):
            assert kind == "axis_value"
        elif math.isclose(a, 0.02, abs_tol=1e-6) and math.isclose(b, 0.45, abs_tol=1e-6):
            assert kind == "setting"  # view 1 there too
        elif int(scene.view_ids[i]) == 1:
            assert kind == "view"
        else:
            assert kind is None
    _, val = split_holdout(scene, holdout)
    assert val is not None
    val_kinds = held_out_kind(val, holdout)
    assert None not in val_kinds
    assert {k: val_kinds.count(k) for k in HELD_OUT_KINDS} == {"view": 6 - 1, "setting": 3, "axis_value": 9}
