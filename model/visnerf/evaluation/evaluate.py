"""Measure a checkpoint against the ground truth of a dataset split: per-frame error and render time.

``evaluate_checkpoint`` renders every frame of the split (or ``max_frames`` evenly chosen ones) with
the checkpoint's own settings at the chosen quality, compares each with its ground-truth image
(PSNR, SSIM, LPIPS where available, mean CIELUV difference), times it, and places it in parameter
space. It also renders the difference examples, runs the render-settings sweep and reads the
training logs. ``report.write_report`` turns the result into files.
"""

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Float, UInt8

from visnerf.checkpoint import CheckpointMeta
from visnerf.data.parsers.cinema_cameras import CinemaCamera
from visnerf.evaluation.colour_difference import DIFFERENCE_SCALE_MAX, luv_difference
from visnerf.evaluation.frames import normalize_params, render_frame
from visnerf.evaluation.ground_truth import EvaluationError, GroundTruth, load_ground_truth
from visnerf.evaluation.metrics import psnr, ssim
from visnerf.evaluation.perceptual import LpipsConfig, load_lpips
from visnerf.evaluation.placement import Placement, classify
from visnerf.evaluation.sweeps import SweepConfig, SweepPoint, run_sweep, sweep_frame_indices, sweep_variants
from visnerf.evaluation.training_curves import TrainingRun, logs_beside, read_training_log
from visnerf.inference import Quality, load_scene
from visnerf.rendering.render_settings import RenderSettings


@dataclass(frozen=True)
class EvalConfig:
    """What an evaluation measures."""

    split: str | None = None
    """Dataset split: ``transforms_<split>.json``; None: ``test``, or every row of a Cinema database."""
    cinema: CinemaCamera | None = None
    """A Cinema database's camera options over its ``visnerf_camera.json``."""
    quality: Quality = "full"
    """Render quality of the per-frame evaluation."""
    max_frames: int | None = None
    """Evaluate this many evenly chosen frames; None: every frame of the split."""
    difference_frames: tuple[int, ...] = ()
    """Frames (split indices) shown as difference images; empty: the worst, median and best by PSNR."""
    n_difference_frames: int = 3
    difference_scale_max: float = DIFFERENCE_SCALE_MAX
    """Delta E*uv at the top of the difference legend."""
    lpips: LpipsConfig = field(default_factory=LpipsConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)
    training_logs: tuple[Path, ...] = ()
    """Training logs of further runs to plot next to the checkpoint's own."""


@dataclass(frozen=True)
class FrameRecord:
    """One evaluated frame."""

    index: int
    """Position in the split."""
    file: str
    params: tuple[float, ...]
    """Raw parameter values in checkpoint axis order."""
    placement: Placement
    psnr: float
    ssim: float
    lpips: float | None
    delta_e_mean: float
    """Mean CIELUV Delta E*uv over the image."""
    ms: float


@dataclass(frozen=True)
class DifferenceExample:
    """A frame shown as synthesized | ground truth | difference."""

    index: int
    reason: str
    synth: UInt8[np.ndarray, "h w 3"]
    truth: UInt8[np.ndarray, "h w 3"]
    delta: Float[np.ndarray, "h w"]
    psnr: float


@dataclass(frozen=True)
class EvalResult:
    """Everything measured; see ``report.write_report``."""

    checkpoint: Path
    data: Path
    split: str
    quality: str
    meta: CheckpointMeta
    frames: tuple[FrameRecord, ...]
    lpips_note: str
    """Which LPIPS network was used, or why LPIPS was not computed."""
    lpips_computed: bool
    differences: tuple[DifferenceExample, ...]
    sweep: tuple[SweepPoint, ...]
    training_runs: tuple[TrainingRun, ...]
    training_note: str
    model_mb: float
    device: str
    torch_threads: int


def _to_uint8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _pick_frames(n: int, max_frames: int | None) -> list[int]:
    if max_frames is None or max_frames >= n:
        return list(range(n))
    if max_frames < 1:
        raise EvaluationError(f"max_frames must be at least 1, got {max_frames}")
    return sorted({int(i) for i in np.linspace(0, n - 1, max_frames).round()})


def _difference_choice(records: list[FrameRecord], cfg: EvalConfig, n_split: int) -> list[tuple[int, str]]:
    """(split index, reason) of the frames shown as difference images."""
    if cfg.difference_frames:
        bad = [i for i in cfg.difference_frames if not 0 <= i < n_split]
        if bad:
            raise EvaluationError(f"difference frame(s) {bad} are outside the split's frames 0..{n_split - 1}")
        return [(int(i), "chosen") for i in dict.fromkeys(cfg.difference_frames)]
    ranked = sorted(records, key=lambda r: (r.psnr, r.index))
    picks = {ranked[0].index: "worst PSNR", ranked[len(ranked) // 2].index: "median PSNR",
             ranked[-1].index: "best PSNR"}
    return list(picks.items())[: max(cfg.n_difference_frames, 0)]


def _training_runs(checkpoint: Path, extra: tuple[Path, ...]) -> tuple[list[TrainingRun], str]:
    runs, notes = [], []
    own = logs_beside(checkpoint)
    if own:
        try:
            runs.append(read_training_log(own[0], name=checkpoint.stem))
        except EvaluationError as exc:
            notes.append(f"the checkpoint's own log is unusable: {exc}")
    else:
        notes.append(f"no training log beside the checkpoint ({checkpoint.with_suffix('.log.csv').name})")
    own_paths = {p.resolve() for p in own}
    runs += [read_training_log(p) for p in dict.fromkeys(extra) if p.resolve() not in own_paths]
    return runs, "; ".join(notes)


def evaluate_checkpoint(
    checkpoint: str | Path, data: str | Path, cfg: EvalConfig, device: torch.device
) -> EvalResult:
    """Measure ``checkpoint`` on ``data``'s ``cfg.split``; raises EvaluationError / CheckpointError."""
    checkpoint, data = Path(checkpoint), Path(data)
    scene = load_scene(checkpoint, device)
    field_, meta = scene.field, scene.meta
    truth: GroundTruth = load_ground_truth(data, cfg.split, meta.param_axes, cfg.cinema)
    gt = truth.scene
    settings = RenderSettings.from_meta(meta, cfg.quality)
    params = torch.stack([normalize_params(meta.param_axes, row) for row in truth.params])  # [n, k]
    placements = classify(meta.param_axes, truth.params)
    scorer, lpips_note = load_lpips(cfg.lpips, device)

    indices = _pick_frames(gt.n_frames, cfg.max_frames)
    render_frame(field_, gt.c2w[indices[0]], gt.intrinsics, params[indices[0]], settings)  # warm-up, untimed
    records = []
    for i in indices:
        frame = render_frame(field_, gt.c2w[i], gt.intrinsics, params[i], settings)
        real = gt.images[i].numpy().astype(np.float32) / 255.0  # [h, w, 3]
        records.append(
            FrameRecord(
                index=i, file=Path(gt.file_paths[i]).name if gt.file_paths else str(i),
                params=tuple(float(v) for v in truth.params[i]), placement=placements[i],
                psnr=psnr(frame.rgb, real), ssim=ssim(frame.rgb, real),
                lpips=None if scorer is None else scorer(frame.rgb, real),
                delta_e_mean=float(luv_difference(frame.rgb, real).mean()), ms=frame.ms,
            )
        )  # fmt: skip

    differences = []
    for i, reason in _difference_choice(records, cfg, gt.n_frames):
        frame = render_frame(field_, gt.c2w[i], gt.intrinsics, params[i], settings)
        real = gt.images[i].numpy()
        differences.append(
            DifferenceExample(index=i, reason=reason, synth=_to_uint8(frame.rgb), truth=real,
                              delta=luv_difference(frame.rgb, real.astype(np.float32) / 255.0),
                              psnr=psnr(frame.rgb, real.astype(np.float32) / 255.0))
        )  # fmt: skip

    sweep: list[SweepPoint] = []
    if cfg.sweep.enabled:
        chosen = torch.tensor(sweep_frame_indices(gt.n_frames, cfg.sweep.n_frames), dtype=torch.long)
        variants = sweep_variants(RenderSettings.from_meta(meta, "full"), RenderSettings.from_meta(meta, "preview"),
                                  cfg.sweep, field_.occupancy is not None)
        sweep = run_sweep(field_, variants, gt.images[chosen], gt.c2w[chosen], gt.intrinsics, params[chosen])

    runs, training_note = _training_runs(checkpoint, cfg.training_logs)
    return EvalResult(
        checkpoint=checkpoint, data=data, split=truth.split, quality=cfg.quality, meta=meta,
        frames=tuple(records), lpips_note=lpips_note, lpips_computed=scorer is not None,
        differences=tuple(differences), sweep=tuple(sweep), training_runs=tuple(runs),
        training_note=training_note, model_mb=checkpoint.stat().st_size / 1e6, device=str(device),
        torch_threads=torch.get_num_threads(),
    )  # fmt: skip

