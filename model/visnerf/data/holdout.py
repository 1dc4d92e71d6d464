"""Split a training set into training and validation frames by view and by parameter setting."""

import torch

from visnerf.checkpoint import ParamAxis
from visnerf.config import HoldoutConfig
from visnerf.data.scene import SceneData, axes_from_values


def split_holdout(scene: SceneData, holdout: HoldoutConfig, atol: float = 1e-6) -> tuple[SceneData, SceneData | None]:
    """(train, val): val holds every frame of a held-out view or a held-out parameter setting.

    The training subset's parameter axes are recomputed from its own values, so an axis keeps only
    values that some training frame has; an axis that becomes constant is an error (nothing would
    be left to learn about it).
    """
    held = torch.zeros(scene.n_frames, dtype=torch.bool)
    for view in holdout.views:
        held |= scene.view_ids == int(view)
    for setting in holdout.settings:
        if len(setting) != scene.n_params:
            raise ValueError(f"held-out setting {setting} has {len(setting)} values, the dataset {scene.n_params}")
        target = torch.tensor(setting, dtype=scene.params.dtype)
        held |= torch.isclose(scene.params, target, atol=atol, rtol=1e-5).all(dim=-1)
    if not held.any():
        return scene, None
    if held.all():
        raise ValueError("the hold-out covers every frame: nothing is left to train on")
    train = scene.subset((~held).nonzero()[:, 0])
    names = [a.name for a in scene.param_axes]
    keep, axes = axes_from_values(names, train.params.double().numpy())
    if len(keep) != len(names):
        raise ValueError("the hold-out leaves a parameter axis with a single training value")
    axes = tuple(_exact_values(a, full) for a, full in zip(axes, scene.param_axes, strict=True))
    train = SceneData(**{**train.__dict__, "param_axes": axes})
    val = scene.subset(held.nonzero()[:, 0])
    val = SceneData(**{**val.__dict__, "param_axes": axes})
    return train, val


def _exact_values(axis: ParamAxis, full: ParamAxis) -> ParamAxis:
    """``axis`` (read back from float32 parameters) with each value replaced by the dataset's exact
    value it came from, so 0.2 stays 0.2 and not 0.20000000298 in checkpoints and the API."""
    def exact(v: float) -> float:
        return min(full.values, key=lambda u: abs(u - v))

    values = tuple(exact(v) for v in axis.values)
    return ParamAxis(axis.name, values[0], values[-1], values, exact(axis.default))
