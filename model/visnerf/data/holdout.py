"""Split a training set into training and validation frames by view, by parameter setting and by
the value of one parameter axis."""

import torch
from torch import Tensor

from visnerf.checkpoint import ParamAxis
from visnerf.config import HoldoutConfig
from visnerf.data.scene import SceneData, axes_from_values


def axis_index(scene: SceneData, axis: str) -> int:
    """The index of a parameter axis named by its name (``OmM``) or by its index (``0``) among the
    scene's varying parameters; ValueError naming the axes the scene has otherwise."""
    names = [a.name for a in scene.param_axes]
    if axis in names:
        return names.index(axis)
    if axis.isdigit():
        return int(axis)  # split_holdout checks its range against the scene
    raise ValueError(f"no parameter axis {axis!r}: this dataset's varying parameters are "
                     + (", ".join(f"{k} {n!r}" for k, n in enumerate(names)) if names else "none (a static scene)")
                     + " (a parameter with one value throughout is dropped when the dataset loads)")


def held_by_axis_value(scene: SceneData, axis: int, value: float, atol: float = 1e-6) -> Tensor:
    """Bool [n]: the frames whose parameter ``axis`` equals ``value`` (within ``atol``, relative
    1e-5, as held-out settings are matched). ValueError when the scene has no such axis."""
    if not 0 <= axis < scene.n_params:
        n = scene.n_params
        raise ValueError(f"held-out axis value ({axis}, {value}): axis {axis} does not exist; this dataset has "
                         + (f"{n} varying parameter{'s' if n > 1 else ''}, axes 0 to {n - 1} ("
                            + ", ".join(a.name for a in scene.param_axes) + ")" if n
                            else "no varying parameter (a static scene)"))
    target = torch.tensor(value, dtype=scene.params.dtype)
    return torch.isclose(scene.params[:, axis], target, atol=atol, rtol=1e-5)


HELD_OUT_KINDS = ("view", "setting", "axis_value")
"""Why a frame is held out: its view (``HoldoutConfig.views``), its whole parameter setting
(``settings``) or one parameter's value (``axis_values``)."""


def _held_by_kind(scene: SceneData, holdout: HoldoutConfig, atol: float) -> dict[str, Tensor]:
    """Bool [n] per kind of ``HELD_OUT_KINDS``: the frames that kind of rule holds out."""
    n = scene.n_frames
    view = torch.zeros(n, dtype=torch.bool)
    for v in holdout.views:
        view |= scene.view_ids == int(v)
    setting = torch.zeros(n, dtype=torch.bool)
    for s in holdout.settings:
        if len(s) != scene.n_params:
            raise ValueError(f"held-out setting {s} has {len(s)} values, the dataset {scene.n_params}")
        target = torch.tensor(s, dtype=scene.params.dtype)
        setting |= torch.isclose(scene.params, target, atol=atol, rtol=1e-5).all(dim=-1)
    axis_value = torch.zeros(n, dtype=torch.bool)
    for axis, value in holdout.axis_values:
        axis_value |= held_by_axis_value(scene, axis, value, atol)
    return {"view": view, "setting": setting, "axis_value": axis_value}


def held_out_kind(scene: SceneData, holdout: HoldoutConfig, atol: float = 1e-6) -> list[str | None]:
    """Why each frame of ``scene`` (the dataset, or the validation frames ``split_holdout`` gave)
    is held out under ``holdout``: one of ``HELD_OUT_KINDS``, None for a frame it keeps. A frame
    held out on several counts takes the one farthest from what training saw: an axis value over a
    setting over a view (a held-out view at a held-out setting is a new setting, one at a held-out
    axis value is a new value)."""
    masks = _held_by_kind(scene, holdout, atol)
    kinds: list[str | None] = [None] * scene.n_frames
    for kind in HELD_OUT_KINDS:  # later kinds overwrite earlier ones
        for i in masks[kind].nonzero()[:, 0].tolist():
            kinds[i] = kind
    return kinds


def split_holdout(scene: SceneData, holdout: HoldoutConfig, atol: float = 1e-6) -> tuple[SceneData, SceneData | None]:
    """(train, val): val holds every frame of a held-out view, a held-out parameter setting or a
    held-out value of one axis (``HoldoutConfig.axis_values``).

    A setting or an axis value that matches no frame holds nothing out (as a view that no frame
    has); an axis index the scene does not have is an error. The training subset's parameter axes
    are recomputed from its own values, so an axis keeps only values that some training frame has;
    an axis that becomes constant is an error (nothing would be left to learn about it).
    """
    held = torch.stack(list(_held_by_kind(scene, holdout, atol).values())).any(dim=0)
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
    values = tuple(full.training_value(v) for v in axis.values)
    return ParamAxis(axis.name, values[0], values[-1], values, full.training_value(axis.default))
