"""The ground truth of an evaluation: one split of a dataset, its parameters in the checkpoint's axes.

The dataset parser drops parameters that are constant within a split, so the split's raw parameter
table is read again here and matched to the checkpoint's axes by name. Every mismatch is an
``EvaluationError`` that names it.
"""

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from jaxtyping import Float

from visnerf.checkpoint import ParamAxis
from visnerf.data.parsers.blender import DatasetError, load_transforms
from visnerf.data.scene import SceneData

SPLITS = ("train", "val", "test")


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


def split_file(data: Path, split: str) -> Path:
    """``data/transforms_<split>.json``; an error naming the file (and the splits present) if absent."""
    if split not in SPLITS:
        raise EvaluationError(f"unknown split {split!r}; use one of {', '.join(SPLITS)}")
    if not data.is_dir():
        raise EvaluationError(f"dataset folder {data} does not exist")
    path = data / f"transforms_{split}.json"
    if not path.is_file():
        present = [p.name for p in sorted(data.glob("transforms_*.json"))]
        raise EvaluationError(
            f"dataset {data} has no {split} split: {path.name} not found "
            f"(present: {', '.join(present) if present else 'no transforms_*.json at all'})"
        )
    return path


def read_param_table(path: Path) -> tuple[list[str], Float[np.ndarray, "n k"]]:
    """Parameter names and raw values of every frame, constant ones included (same rules as the parser)."""
    meta = json.loads(path.read_text())
    frames = meta.get("frames") or []
    rows = []
    for frame in frames:
        if "params" in frame:
            rows.append([float(v) for v in frame["params"]])
        elif "time" in frame:
            rows.append([float(frame["time"])])
        else:
            rows.append([])
    k = len(rows[0]) if rows else 0
    values = np.asarray(rows, dtype=np.float64).reshape(len(rows), k)
    default_names = ["time"] if frames and "time" in frames[0] and "params" not in frames[0] else [f"p{j}" for j in range(k)]
    names = [str(n) for n in (meta.get("param_names") or default_names)]
    return names, values


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


def load_ground_truth(data: str | Path, split: str, axes: tuple[ParamAxis, ...]) -> GroundTruth:
    """Load ``data/transforms_<split>.json`` and match its parameters to ``axes``."""
    data = Path(data)
    path = split_file(data, split)
    try:
        scene = load_transforms(path)
        names, values = read_param_table(path)
    except DatasetError as exc:
        raise EvaluationError(f"ground truth of the {split} split cannot be read: {exc}") from None
    except (json.JSONDecodeError, ValueError, TypeError) as exc:
        raise EvaluationError(f"{path}: cannot read the parameter values: {exc}") from None
    params = align_params(axes, names, values)
    if not np.all(np.isfinite(params)) or any(not math.isfinite(a.max - a.min) for a in axes):
        raise EvaluationError(f"{path}: parameter values must be finite")
    return GroundTruth(scene=scene, params=params, split=split, source=path)
