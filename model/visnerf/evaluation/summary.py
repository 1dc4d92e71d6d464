"""Aggregate per-frame records: overall figures and the split by place in parameter space."""

import math
from collections.abc import Callable

import numpy as np

from visnerf.evaluation.evaluate import FrameRecord


def _mean(values: list[float]) -> float | None:
    return float(np.mean(values)) if values else None


def aggregate(records: list[FrameRecord]) -> dict:
    """Frame count, mean PSNR / SSIM / LPIPS / Delta E, render time (median and mean); None when empty.

    LPIPS is None unless every frame has it. A frame identical to its ground truth has infinite PSNR,
    and so has the mean then.
    """
    lpips = [r.lpips for r in records]
    ms = [r.ms for r in records]
    return {
        "n": len(records),
        "psnr": _mean([r.psnr for r in records]),
        "ssim": _mean([r.ssim for r in records]),
        "lpips": _mean([v for v in lpips if v is not None]) if records and None not in lpips else None,
        "delta_e_mean": _mean([r.delta_e_mean for r in records]),
        "ms_median": float(np.median(ms)) if ms else None,
        "ms_mean": _mean(ms),
    }


_GROUPS: dict[str, tuple[str, Callable[[FrameRecord], bool]]] = {
    "at_training_values": ("every parameter at a training value", lambda r: r.placement.at_training_values),
    "between_training_values": ("between training values (interpolated)",
                                lambda r: not r.placement.at_training_values),
    "one_moving": ("one parameter moving", lambda r: r.placement.motion == "one"),
    "all_moving": ("all parameters moving", lambda r: r.placement.motion == "all"),
    "some_moving": ("some but not all parameters moving", lambda r: r.placement.motion == "some"),
    "none_moving": ("no parameter moving (camera only)", lambda r: r.placement.motion == "none"),
}  # fmt: skip


def group_label(record: FrameRecord, n_params: int) -> str:
    """The per-frame plot's group of a frame."""
    where = "at training values" if record.placement.at_training_values else "between training values"
    if n_params >= 2:
        return f"{where}, {record.placement.motion} moving"
    return where


def parameter_space_groups(records: list[FrameRecord], n_params: int) -> dict:
    """Error at training values vs between them and, for K >= 2, one parameter moving vs all moving.

    Every group is present (``n`` = 0 and None figures when no frame falls in it); motion groups
    other than ``one`` / ``all`` appear only when some frame is in them.
    """
    names = ["at_training_values", "between_training_values"]
    if n_params >= 2:
        names += ["one_moving", "all_moving"]
        names += [g for g in ("some_moving", "none_moving") if any(_GROUPS[g][1](r) for r in records)]
    out = {}
    for name in names:
        description, member = _GROUPS[name]
        out[name] = {"description": description, **aggregate([r for r in records if member(r)])}
    return out


def json_safe(value: object) -> object:
    """Infinite floats become the strings ``"inf"`` / ``"-inf"`` and NaN becomes None (strict JSON)."""
    if isinstance(value, float):
        if math.isnan(value):
            return None
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return value
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value
