"""``Provenance``: how a checkpoint was made (stored in its metadata as ``provenance``): the data,
the steps and seconds, the last validation, the schedule's position, the whole training
configuration, what the recipe chose and why, and the ranks that trained it."""

import math
import numbers
from dataclasses import asdict, dataclass, field, fields
from typing import Any


class ProvenanceError(ValueError):
    """A provenance record that is not one: names the key and the problem."""


@dataclass(frozen=True)
class RecipeChoice:
    """One setting the recipe chose from the data, and why (``training.recipe.Choice``)."""

    name: str
    value: Any
    reason: str


@dataclass(frozen=True)
class RunStates:
    """The run states a run wrote while it trained (``training.resume``) and the seconds they took."""

    written: int = 0
    seconds: float = 0.0


@dataclass(frozen=True)
class Provenance:
    """The provenance record of a checkpoint."""

    dataset: str = ""
    """The training data's folder (or the name a caller gave)."""
    iterations: int = 0
    train_seconds: float = 0.0
    """Training time, validation and run states excluded."""
    val_psnr: float | None = None
    """The last validation's PSNR (dB) and SSIM; None where nothing was held out."""
    val_ssim: float | None = None
    seed: int | None = None
    upsamples_done: int = 0
    """The schedule's position: grid upsamplings, occupancy builds and refinements done."""
    occupancy_done: int = 0
    refines_done: int = 0
    full_spacing: str | None = None
    """How the full-quality spacing was chosen (``evaluation.spacing``)."""
    run_states: RunStates = field(default_factory=RunStates)
    recipe: dict[str, Any] = field(default_factory=dict)
    """The whole ``TrainConfig`` of the run (``visnerf info`` shows it; a run from this checkpoint
    starts from it)."""
    choices: tuple[RecipeChoice, ...] = ()
    dataset_notes: tuple[str, ...] = ()
    """How the dataset was read (a Cinema database's columns, say)."""
    ranks: int = 1
    """Processes that trained it (``training.distributed``), their backend and launcher."""
    backend: str | None = None
    launcher: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The JSON document (a run of one process records no ranks, backend or launcher)."""
        data = asdict(self)
        data["choices"] = [asdict(c) for c in self.choices]
        data["dataset_notes"] = list(self.dataset_notes)
        if self.ranks == 1:
            for key in ("ranks", "backend", "launcher"):
                data.pop(key)
        return data

    @classmethod
    def from_dict(cls, data: Any) -> "Provenance":
        """The record in a checkpoint's metadata; ProvenanceError names an unknown key or a value
        of the wrong kind."""
        if not isinstance(data, dict):
            raise ProvenanceError(f"provenance must be an object, got {type(data).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ProvenanceError(f"provenance: unknown key(s) {unknown}")
        values = dict(data)
        for name in ("iterations", "upsamples_done", "occupancy_done", "refines_done", "ranks"):
            if name in values:
                values[name] = _whole(name, values[name])
        if values.get("seed") is not None:
            values["seed"] = _whole("seed", values["seed"])
        if "train_seconds" in values:
            values["train_seconds"] = _number("train_seconds", values["train_seconds"])
        for name in ("val_psnr", "val_ssim"):
            if values.get(name) is not None:
                values[name] = _number(name, values[name])
        for name in ("dataset", "full_spacing", "backend", "launcher"):
            if values.get(name) is not None and not isinstance(values[name], str):
                raise ProvenanceError(f"provenance: {name} must be text, got {values[name]!r}")
        if "run_states" in values:
            states = _object("run_states", values["run_states"])
            values["run_states"] = RunStates(_whole("run_states.written", states.get("written", 0)),
                                             _number("run_states.seconds", states.get("seconds", 0.0)))
        if "recipe" in values:
            values["recipe"] = dict(_object("recipe", values["recipe"]))
        if "choices" in values:
            values["choices"] = tuple(_choice(i, c) for i, c in enumerate(_list("choices", values["choices"])))
        if "dataset_notes" in values:
            notes = _list("dataset_notes", values["dataset_notes"])
            if not all(isinstance(n, str) for n in notes):
                raise ProvenanceError("provenance: dataset_notes must be lines of text")
            values["dataset_notes"] = tuple(notes)
        return cls(**values)


def _whole(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 0:
        raise ProvenanceError(f"provenance: {name} must be a whole number of at least 0, got {value!r}")
    return int(value)


def _number(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise ProvenanceError(f"provenance: {name} must be a finite number, got {value!r}")
    return float(value)


def _object(name: str, value: Any) -> dict:
    if not isinstance(value, dict):
        raise ProvenanceError(f"provenance: {name} must be an object, got {value!r}")
    return value


def _list(name: str, value: Any) -> list:
    if not isinstance(value, list | tuple):
        raise ProvenanceError(f"provenance: {name} must be a list, got {value!r}")
    return list(value)


def _choice(index: int, value: Any) -> RecipeChoice:
    item = _object(f"choices[{index}]", value)
    if (set(item) != {"name", "value", "reason"} or not isinstance(item["name"], str)
            or not isinstance(item["reason"], str)):
        raise ProvenanceError(f"provenance: choices[{index}] must have a name, a value and a reason, got {item!r}")
    return RecipeChoice(item["name"], item["value"], item["reason"])
