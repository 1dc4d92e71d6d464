"""What a training run records: validations, the log, the weight average and the checkpoint."""

import csv
import json
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from visnerf.checkpoint import CheckpointMeta, save_checkpoint
from visnerf.config import RenderConfig
from visnerf.data.scene import SceneData
from visnerf.evaluation.metrics import psnr, ssim
from visnerf.provenance import Provenance
from visnerf.rendering.render_settings import RenderSettings
from visnerf.rendering.renderer import render_image
from visnerf.representation.field import VisNerfField
from visnerf.training.weight_average import WeightAverage


@torch.no_grad()
def validate(
    field_: VisNerfField, scene: SceneData, render_cfg: RenderConfig, max_images: int
) -> dict[str, float]:
    """Mean PSNR / SSIM over up to ``max_images`` evenly chosen frames of ``scene``."""
    idx = np.linspace(0, scene.n_frames - 1, min(max_images, scene.n_frames)).round().astype(int)
    settings = RenderSettings.from_config(render_cfg, scene.background)
    params = scene.normalized_params()
    psnrs, ssims, ms = [], [], []
    field_.eval()
    for i in np.unique(idx):
        t0 = time.perf_counter()
        with torch.inference_mode():
            img = render_image(field_, scene.c2w[i].to(field_.device), scene.intrinsics,
                               params[i].to(field_.device), settings)
        ms.append(1000 * (time.perf_counter() - t0))
        pred = img.clamp(0, 1).cpu().numpy()
        gt = scene.images[i].numpy().astype(np.float32) / 255.0
        psnrs.append(psnr(pred, gt))
        ssims.append(ssim(pred, gt))
    field_.train()
    return {"val_psnr": float(np.mean(psnrs)), "val_ssim": float(np.mean(ssims)),
            "val_ms_per_frame": float(np.median(ms))}


def write_log(rows: list[dict], path: Path) -> None:
    if not rows:
        return
    keys = list(dict.fromkeys(k for row in rows for k in row))
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
    path.with_suffix(".json").write_text(json.dumps(rows, indent=1))


class Recording:
    """The trainer's records (a part of ``Trainer``)."""

    def _average_weights(self) -> None:
        """Keep the parameters' moving average from ``weight_average_from`` on, every
        ``weight_average_every`` steps; (re)start it where it does not follow the field's current
        parameters (none yet, or the grid was upsampled since)."""
        cfg = self.cfg
        p = self.progress()
        if cfg.weight_average_span <= 0.0 or p < cfg.weight_average_from:
            return
        if self.weight_average is None or not self.weight_average.follows(self.field):
            self.weight_average = WeightAverage.start(self.field, cfg.weight_average_span, p)
        elif self.state.iteration % cfg.weight_average_every == 0:
            self.weight_average.update(p)

    def _use_weight_average(self) -> dict[str, float]:
        """At the end of training, replace the parameters by their moving average (if one is kept).
        With validation frames, returns the last live parameters' and the average's validation
        PSNR on them, both rendered the same way just before and after the swap (before the final
        occupancy grid and spacing), so that a run's log compares the two."""
        average = self.weight_average
        if average is None or not average.follows(self.field):
            return {}
        average.update(self.progress())
        compared = {}
        if self.val_scene is not None:
            compared["live_val_psnr"] = validate(self.field, self.val_scene, self.render_cfg,
                                                 self.cfg.validate_max_images)["val_psnr"]
        try:
            average.copy_into(self.field)
        except FloatingPointError as exc:  # the run's result stays: the last parameters, unchanged
            warnings.warn(f"{exc}; the checkpoint holds the last parameters", RuntimeWarning, stacklevel=2)
            return compared
        if self.val_scene is not None:
            compared["average_val_psnr"] = validate(self.field, self.val_scene, self.render_cfg,
                                                    self.cfg.validate_max_images)["val_psnr"]
        return compared

    def _record(self, train_psnr: float, wall0: float, on_validate: Callable | None,
                extra: dict[str, float] | None = None) -> None:
        row = {"iteration": self.state.iteration, "train_seconds": round(self.state.train_seconds, 2),
               "wall_seconds": round(time.perf_counter() - wall0, 2), "train_psnr": round(train_psnr, 3),
               "resolution": self.field.resolution[0]}
        if self.field.occupancy is not None:
            row["occupied_cells"] = int(self.field.occupancy.sum())
        if self.val_scene is not None:
            row.update({k: round(v, 4) for k, v in validate(self.field, self.val_scene, self.render_cfg,
                                                              self.cfg.validate_max_images).items()})
        row.update({k: round(v, 4) for k, v in (extra or {}).items()})
        self.state.log.append(row)
        if on_validate is not None:
            on_validate(row)

    def save(self, path: str | Path, dataset: str = "") -> Path:
        """Checkpoint plus the training log (``<stem>.log.csv`` and ``.json``) beside it."""
        path = Path(path)
        s = self.scene
        last = self.state.log[-1] if self.state.log else {}
        meta = CheckpointMeta(
            field=self.field.current_config(),
            render=self.render_cfg,
            param_axes=s.param_axes,
            bbox=tuple(tuple(float(x) for x in c) for c in self.field.aabb.cpu()),  # type: ignore[arg-type]
            background=s.background,
            camera=s.default_camera(),
            image_width=s.intrinsics.width,
            image_height=s.intrinsics.height,
            title=s.title,
            kind=s.kind,
            provenance=Provenance.from_dict({
                "dataset": dataset or s.source, "iterations": self.state.iteration,
                "train_seconds": round(self.state.train_seconds, 1),
                "val_psnr": last.get("val_psnr"), "val_ssim": last.get("val_ssim"),
                "seed": self.cfg.seed, "upsamples_done": self.state.upsamples_done,
                "occupancy_done": self.state.occupancy_done,
                "refines_done": self.state.refines_done, "full_spacing": self.spacing_note,
                "run_states": {"written": self.state.states_written, "seconds": round(self.state.state_seconds, 2)},
                "recipe": self.cfg.to_dict(), "choices": self.recipe_choices, "dataset_notes": self.dataset_notes,
                **self.ranks.provenance()}),
        )
        save_checkpoint(self.field, meta, path)
        write_log(self.state.log, path.with_suffix(".log.csv"))
        return path
