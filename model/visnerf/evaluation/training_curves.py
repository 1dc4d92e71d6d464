"""Error against training time, from the logs that ``Trainer.save`` writes beside a checkpoint.

A log is ``<ckpt stem>.log.csv`` (or the same rows as ``.log.json``): one row per validation with
``iteration``, ``train_seconds`` (training time, validation excluded), ``wall_seconds`` and
``val_psnr`` (when the run had held-out frames) or at least ``train_psnr``.
"""

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

from visnerf.evaluation.ground_truth import EvaluationError

_COLUMNS = ("iteration", "train_seconds", "wall_seconds", "train_psnr", "val_psnr", "val_ssim")


@dataclass(frozen=True)
class CurvePoint:
    """One logged validation."""

    iteration: int
    train_seconds: float
    wall_seconds: float
    psnr: float
    """Validation PSNR, or the training PSNR for a run that held nothing out (see ``TrainingRun.metric``)."""
    ssim: float | None


@dataclass(frozen=True)
class TrainingRun:
    """The curve of one training run."""

    name: str
    source: Path
    metric: str
    """``val_psnr`` or, without validation frames, ``train_psnr``."""
    points: tuple[CurvePoint, ...]


def logs_beside(checkpoint: Path) -> list[Path]:
    """The checkpoint's own training log, if one was written beside it (the CSV preferred)."""
    for suffix in (".log.csv", ".log.json"):
        path = checkpoint.with_suffix(suffix)
        if path.is_file():
            return [path]
    return []


def _number(value: object) -> float:
    if value is None or value == "":
        return math.nan
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.nan


def _read_rows(path: Path) -> list[dict]:
    try:
        if path.suffix == ".json":
            rows = json.loads(path.read_text())
            if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
                raise EvaluationError(f"training log {path} is not a JSON list of rows")
            return rows
        with path.open(newline="") as fh:
            return list(csv.DictReader(fh))
    except OSError as exc:
        raise EvaluationError(f"cannot read training log {path}: {exc.strerror}") from None
    except json.JSONDecodeError as exc:
        raise EvaluationError(f"training log {path} is not valid JSON: {exc}") from None


def read_training_log(path: str | Path, name: str | None = None) -> TrainingRun:
    """One run's curve; an error naming the file if it has no usable rows."""
    path = Path(path)
    rows = [{k: _number(row.get(k)) for k in _COLUMNS} for row in _read_rows(path)]
    has_val = any(math.isfinite(r["val_psnr"]) for r in rows)
    metric = "val_psnr" if has_val else "train_psnr"
    points = tuple(
        CurvePoint(
            iteration=int(r["iteration"]) if math.isfinite(r["iteration"]) else 0,
            train_seconds=r["train_seconds"],
            wall_seconds=r["wall_seconds"],
            psnr=r[metric],
            ssim=r["val_ssim"] if has_val and math.isfinite(r["val_ssim"]) else None,
        )
        for r in rows
        if math.isfinite(r["train_seconds"]) and math.isfinite(r[metric])
    )
    if not points:
        raise EvaluationError(f"training log {path} has no row with train_seconds and a PSNR")
    run_name = name or path.name.removesuffix(".csv").removesuffix(".json").removesuffix(".log")
    return TrainingRun(name=run_name, source=path, metric=metric, points=points)
