"""A training run's state, written and read back to go on bit for bit (``run_state.py`` holds the file format)."""

import time
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from visnerf.config import FieldConfig, RenderConfig, TrainConfig
from visnerf.data.scene import SceneData
from visnerf.representation.field import VisNerfField
from visnerf.training.run_state import (
    RunStateError,
    pack_optimizer,
    read_run_state,
    scene_fingerprint,
    unpack_optimizer,
    write_run_state,
)
from visnerf.training.schedule import TrainState
from visnerf.training.weight_average import WeightAverage

if TYPE_CHECKING:
    from visnerf.training.trainer import Trainer


class Resumable:
    """Writing and reading the trainer's run state (a part of ``Trainer``)."""

    def write_run_state(self, path: Path) -> Path:
        """Write everything this run needs to go on (``run_state.py``); the time it takes counts
        as training time (``TrainState.state_seconds``)."""
        t0 = time.perf_counter()
        tensors, document = self.capture_run_state()
        write_run_state(path, tensors, document)
        dt = time.perf_counter() - t0
        self.state.states_written += 1
        self.state.state_seconds += dt
        self.state.train_seconds += dt
        return path

    def capture_run_state(self) -> tuple[dict[str, Tensor], dict[str, Any]]:
        """(tensors, JSON document) of the run as it stands between two steps."""
        tensors = {f"field.{name}": value.float() if value.is_floating_point() else value
                   for name, value in self.field.state_dict().items() if name != "occupancy"}
        if self.field.occupancy is not None:
            tensors["occupancy"] = self.field.occupancy.to(torch.uint8)
        optimizer_tensors, optimizer_doc = pack_optimizer(self.optimizer)
        tensors.update(optimizer_tensors)
        average = None
        if self.weight_average is not None and self.weight_average.follows(self.field):
            tensors.update({f"average.{i}": a for i, a in enumerate(self.weight_average.average)})
            average = {"span": self.weight_average.span, "progress": self.weight_average.progress}
        tensors["rng.torch"] = torch.get_rng_state()
        tensors["rng.generator"] = self.generator.get_state()
        if self.device.type == "cuda":
            tensors["rng.cuda"] = torch.cuda.get_rng_state(self.device)
        if self.carved is not None:
            tensors["carved.grid"], tensors["carved.box"] = self.carved[0].to(torch.uint8), self.carved[1]
        tensors["settings"] = self.settings_all
        document = {
            "scene": scene_fingerprint(self.scene),
            "state": asdict(self.state),
            "train": self.cfg.to_dict(),
            "field": self.field.current_config().to_dict(),
            "render": self.render_cfg.to_dict(),
            "choices": self.recipe_choices,
            "dataset_notes": self.dataset_notes,
            "setup_seconds": self.setup_seconds,
            "ema_mse": self.ema_mse,
            "optimizer": optimizer_doc,
            "weight_average": average,
        }
        return tensors, document

    @classmethod
    def from_run_state(
        cls,
        path: Path,
        train_scene: SceneData,
        val_scene: SceneData | None,
        device: torch.device,
        train_overrides: dict[str, Any] | None = None,
        render_overrides: dict[str, Any] | None = None,
    ) -> "Trainer":
        """The run saved at ``path``, ready to go on where it stopped: the same field, optimizer
        moments, weight average, random state, occupancy and schedule position. The training
        configuration is the run's, with ``train_overrides`` (a longer budget, say) on top.
        ``RunStateError`` if the file is unusable or was written for other training frames."""
        document, tensors = read_run_state(path)
        if document["scene"] != scene_fingerprint(train_scene):
            raise RunStateError(f"{path} was written for other training frames (another dataset, split or "
                                "hold-out); resume with the data and hold-out options of the run that wrote it")
        try:
            cfg = TrainConfig.from_dict({**document["train"], **(train_overrides or {})})
            render_cfg = RenderConfig.from_dict({**document["render"], **(render_overrides or {})})
            field_cfg = FieldConfig.from_dict(document["field"])
            start = TrainState(**document["state"])
        except (KeyError, TypeError, ValueError) as exc:
            raise RunStateError(f"{path}: the run's configuration cannot be read back: {exc}") from None
        field_ = VisNerfField(field_cfg, tensors["field.aabb"])
        try:
            field_.load_state_dict({name[len("field."):]: value for name, value in tensors.items()
                                    if name.startswith("field.")}, strict=True)
        except RuntimeError as exc:
            raise RunStateError(f"{path}: the field's tensors do not match its configuration: {exc}") from None
        if "occupancy" in tensors:
            field_.set_occupancy(tensors["occupancy"].bool())
        trainer = cls(train_scene, val_scene, cfg, device, render_cfg=render_cfg, init_field=field_, start=start)
        trainer._restore(document, tensors)
        return trainer

    def _restore(self, document: dict[str, Any], tensors: dict[str, Tensor]) -> None:
        """Put back what ``capture_run_state`` saved beyond the field and the schedule."""
        unpack_optimizer(self.optimizer, tensors, document["optimizer"])
        average = document.get("weight_average")
        if average is not None:
            live = list(self.field.parameters())
            saved = [tensors[f"average.{i}"].to(self.device) for i in range(len(live))]
            self.weight_average = WeightAverage(float(average["span"]), live, saved, float(average["progress"]))
        torch.set_rng_state(tensors["rng.torch"])
        self.generator.set_state(tensors["rng.generator"])
        if "rng.cuda" in tensors and self.device.type == "cuda":
            torch.cuda.set_rng_state(tensors["rng.cuda"], self.device)
        if "carved.grid" in tensors:
            self.carved = (tensors["carved.grid"].bool(), tensors["carved.box"].float())
        self.settings_all = tensors["settings"]
        self.recipe_choices = list(document.get("choices", []))
        self.dataset_notes = list(document.get("dataset_notes", []))
        self.setup_seconds = float(document.get("setup_seconds", 0.0))
        self.ema_mse = document.get("ema_mse")
