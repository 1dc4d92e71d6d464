"""The ground truth of an evaluation: one split of a dataset, its parameters in the checkpoint's axes.

The dataset reader (``data.datasets``) drops parameters that are constant within a split; its full
parameter table is matched here to the checkpoint's axes by name. Every mismatch is an
``EvaluationError`` that names it.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from jaxtyping import Float

from visnerf.checkpoint import ParamAxis
from visnerf.data.datasets import SPLITS, DatasetError, has_split, is_cinema_database, read_split
from visnerf.data.parsers.cinema_cameras import CinemaCamera
from visnerf.data.scene import SceneData


class EvaluationError(ValueError):
    """An evaluation cannot run; the message names the problem."""


@dataclass(frozen=True)
class GroundTruth:
    """Frames of one split with their raw parameter values in checkpoint axis order."""

    scene: SceneData
    params: Float[np.ndarray, "n k"]
    """Raw parameter values, one column per checkpoint axis."""
    split: str
    source: Path


def check_split(data: Path, split: str | None) -> str:
    """The split to read: ``split``, or ``test`` (a Cinema database: its rows, with no split named)."""
    if split is not None and split not in SPLITS:
        raise EvaluationError(f"unknown split {split!r}; use one of {', '.join(SPLITS)}")
    if is_cinema_database(data):
        if split is not None:
            raise EvaluationError(f"{data} is a Cinema database, which has no splits: every row is scored "
                                  "(leave out --split)")
        return "train"
    split = split or "test"
    if not data.is_dir():
        raise EvaluationError(f"dataset folder {data} does not exist")
    if not has_split(data, split):
        present = [p.name for p in sorted(data.glob("transforms_*.json"))]
        raise EvaluationError(
            f"dataset {data} has no {split} split: transforms_{split}.json not found "
            f"(present: {', '.join(present) if present else 'no transforms_*.json at all'})"
        )
    return split


def align_params(
    axes: tuple[ParamAxis, ...], names: list[str], values: Float[np.ndarray, "n j"]
) -> Float[np.ndarray, "n k"]:
    """The dataset's values in checkpoint axis order, checked against each axis' training range."""
    dataset_axes = f"dataset parameters {names if names else '(none)'}"
    ckpt_axes = f"checkpoint axes {[a.name for a in axes] if axes else '(none: a static scene)'}"
    missing = [a.name for a in axes if a.name not in names]
    if missing:
        raise EvaluationError(
            f"parameter axes do not match: the dataset lacks {missing} ({ckpt_axes}, {dataset_axes})"
        )
    axis_names = {a.name for a in axes}
    varying_extra = [
        n for j, n in enumerate(names) if n not in axis_names and np.unique(values[:, j]).size > 1
    ]
    if varying_extra:
        raise EvaluationError(
            f"parameter axes do not match: the dataset varies {varying_extra}, which the checkpoint has no "
            f"axis for ({ckpt_axes}, {dataset_axes})"
        )
    columns = []
    for axis in axes:
        column = values[:, names.index(axis.name)]
        tol = 1e-6 * max(1.0, abs(axis.max - axis.min))
        outside = np.nonzero((column < axis.min - tol) | (column > axis.max + tol))[0]
        if outside.size:
            i = int(outside[0])
            raise EvaluationError(
                f"frame {i}: parameter {axis.name!r}={column[i]:g} lies outside the checkpoint's range "
                f"[{axis.min:g}, {axis.max:g}] ({outside.size} frame(s) do); the model only interpolates"
            )
        columns.append(np.clip(column, axis.min, axis.max))
    return np.stack(columns, axis=-1) if columns else np.zeros((values.shape[0], 0))


def load_ground_truth(
    data: str | Path, split: str | None, axes: tuple[ParamAxis, ...], cinema: CinemaCamera | None = None
) -> GroundTruth:
    """Load one split (None: ``test``, or a Cinema database's rows) and match its parameters to ``axes``."""
    data = Path(data)
    split = check_split(data, split)
    try:
        parsed = read_split(data, split, cinema)
    except DatasetError as exc:
        raise EvaluationError(f"ground truth of the {split} split cannot be read: {exc}") from None
    source = Path(parsed.scene.source)
    params = align_params(axes, list(parsed.param_names), parsed.param_values)
    if not np.all(np.isfinite(params)) or any(not math.isfinite(a.max - a.min) for a in axes):
        raise EvaluationError(f"{source}: parameter values must be finite")
    label = "all rows" if is_cinema_database(data) else split
    return GroundTruth(scene=parsed.scene, params=params, split=label, source=source)
