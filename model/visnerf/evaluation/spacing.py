"""Choosing a checkpoint's full-quality sample spacing from measured frames.

Full-quality frames march with ``RenderConfig.full_step_ratio`` voxels between samples; training
uses ``step_ratio`` and the exhaustive reference the finer of that and half a voxel. How coarse a
spacing a model tolerates depends on the model: on the bundled scenes one voxel is as good as
half a voxel against ground truth, on a Nyx model with sharp filaments one voxel lost 0.3 dB and
three quarters 0.07 dB. Each voxel of spacing saved is frame time saved (one voxel takes about
0.75 of the time of three quarters), so the spacing is chosen per checkpoint: render held-out
frames exhaustively and at each candidate, and keep the coarsest candidate whose mean PSNR
against the ground truth is within ``tolerance_db`` of the exhaustive frames'. The default, 0.05 dB,
is half the fast renderer's accuracy target, because a few frames do not speak for all: on the
60-minute Nyx model one voxel was 0.045 dB below the exhaustive frames on 8 validation frames and
0.147 dB below on the 20 frames of bench/render_speed.py. Training does it at the end (``Trainer.run``)
on its validation frames, or on its training frames where none are held out: the choice weighs
sampling error, which training frames show as well; ``visnerf calibrate`` does it for an existing
checkpoint.

The exhaustive reference (``RenderSettings.from_config(..., "exhaustive")``) marches the
checkpoint's occupancy grid, as the candidates do: the grid a training run leaves is part of the
model (the cells it kept fitting, ``Trainer.finish_occupancy``), and outside it the density has
had no photometric loss since the grid was last narrowed. Without the grid, the reference of the
60-minute Nyx model whose refined grids hold no ring of empty cells rendered that untrained
density: 26.195 dB on 6 frames against 26.849 dB at three quarters of a voxel, every candidate
only 33 to 34 dB from it, so the choice fell back to half a voxel. Only the spacing differs
between the reference and the candidates this way.
"""

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from visnerf.config import RenderConfig
from visnerf.data.scene import SceneData
from visnerf.evaluation.metrics import psnr
from visnerf.rendering.render_settings import RenderSettings, exhaustive_step_ratio
from visnerf.rendering.renderer import render_image
from visnerf.representation.field import VisNerfField

MIN_AGREEMENT_DB = 38.0
"""Candidate frames must also stay this close (mean PSNR) to the exhaustive frames. Against ground
truth a coarser spacing can win on some frames and lose on others: the Nyx model trained one
voxel apart was 0.31 dB above the exhaustive frames on its 24 validation frames at one voxel and
0.147 dB below on the 20 frames of bench/render_speed.py, its one-voxel frames 36 dB from the
exhaustive ones; at three quarters of a voxel 40 dB, and 0.005 dB above on those 20. The bundled
scenes' one-voxel frames are 52 to 54 dB from theirs."""

CANDIDATES = (1.5, 1.25, 1.0, 0.75)
"""Spacings tried, coarsest first, in voxels; the exhaustive spacing is the fallback. Those above
one voxel are for models trained with samples more than a voxel apart (``RenderConfig.step_ratio``)."""


@dataclass(frozen=True)
class SpacingChoice:
    ratio: float
    """The chosen full-quality spacing in voxels."""
    exhaustive_psnr: float
    """Mean PSNR of the exhaustive frames against the ground truth."""
    candidate_psnr: dict[float, float]
    """Mean PSNR of the full-quality frames at each candidate spacing tried."""
    frames: int
    agreement_db: dict[float, float] = field(default_factory=dict)
    """Mean PSNR of the frames at each candidate against the exhaustive frames."""

    def describe(self, training_frames: bool = False) -> str:
        """The choice and what each candidate scored; ``training_frames``: it was made on training
        frames because none were held out, and the note says so."""
        tried = ", ".join(f"{r:g} voxel {p:.3f} dB ({self.agreement_db.get(r, float('nan')):.1f} dB from exhaustive)"
                          for r, p in self.candidate_psnr.items())
        return (f"full-quality spacing {self.ratio:g} voxel (exhaustive {self.exhaustive_psnr:.3f} dB; {tried}; "
                f"mean over {self.frames} frames)" + (", training frames (none held out)" if training_frames else ""))


@torch.no_grad()
def choose_full_spacing(
    field: VisNerfField,
    scene: SceneData,
    render_cfg: RenderConfig,
    max_frames: int = 8,
    tolerance_db: float = 0.05,
    candidates: tuple[float, ...] = CANDIDATES,
    min_agreement_db: float = MIN_AGREEMENT_DB,
) -> SpacingChoice:
    """The coarsest of ``candidates`` and the exhaustive spacing (``exhaustive_step_ratio``) whose
    full-quality frames of ``scene`` (up to ``max_frames``, evenly chosen) lose at most
    ``tolerance_db`` mean PSNR against the exhaustive frames, both against the ground truth, and
    are at least ``min_agreement_db`` (mean PSNR) from the exhaustive frames themselves; when none
    does, the coarsest near the best of them (``_near_the_best_measured``). Candidates
    render with the full-quality settings of ``render_cfg`` otherwise (occupancy, early
    termination, colour threshold); the reference with the exhaustive ones (every sample, float32),
    within the field's occupancy grid."""
    if scene.n_frames == 0:
        raise ValueError("no frames to choose the full-quality spacing on")
    if max_frames < 1:
        raise ValueError(f"max_frames must be at least 1, got {max_frames}")
    if not tolerance_db >= 0.0:
        raise ValueError(f"tolerance_db must be >= 0, got {tolerance_db}")
    device = field.aabb.device
    idx = np.unique(np.linspace(0, scene.n_frames - 1, min(max_frames, scene.n_frames)).round().astype(int))
    params = scene.normalized_params()
    truth = [scene.images[i].numpy().astype(np.float32) / 255.0 for i in idx]

    def render_all(settings: RenderSettings) -> list[np.ndarray]:
        with torch.inference_mode():
            return [render_image(field, scene.c2w[i].to(device), scene.intrinsics, params[i].to(device),
                                 settings).clamp(0, 1).cpu().numpy() for i in idx]

    def mean_psnr(frames: list[np.ndarray], against: list[np.ndarray]) -> float:
        return float(np.mean([psnr(a, b) for a, b in zip(frames, against, strict=True)]))

    was_training = field.training
    field.eval()
    try:
        reference = render_all(RenderSettings.from_config(render_cfg, scene.background, "exhaustive"))
        exhaustive = mean_psnr(reference, truth)
        full = RenderSettings.from_config(render_cfg, scene.background, "full")
        tried: dict[float, float] = {}
        agreement: dict[float, float] = {}
        finest = exhaustive_step_ratio(render_cfg)
        chosen = None
        for ratio in [*sorted((c for c in candidates if c > finest), reverse=True), finest]:
            frames = render_all(replace(full, step_ratio=ratio))
            tried[ratio], agreement[ratio] = mean_psnr(frames, truth), mean_psnr(frames, reference)
            if tried[ratio] >= exhaustive - tolerance_db and agreement[ratio] >= min_agreement_db:
                chosen = ratio
                break
        if chosen is None:
            chosen = _near_the_best_measured(tried, agreement, tolerance_db, min_agreement_db, finest)
    finally:
        field.train(was_training)
    return SpacingChoice(chosen, exhaustive, tried, len(idx), agreement)


def _near_the_best_measured(tried: dict[float, float], agreement: dict[float, float], tolerance_db: float,
                            min_agreement_db: float, finest: float) -> float:
    """When no spacing is within the tolerance of the exhaustive frames: the coarsest whose
    full-quality frames are within it of the best full-quality frames measured, among those that
    agree with the exhaustive frames (the finest spacing when none does). What full quality loses
    at every spacing (colour decoded only above a weight, early termination, bfloat16) is not the
    spacing's to win back: on the bundled plume_time every spacing from 1.5 to 0.5 voxel was 0.07
    to 0.11 dB below the exhaustive frames, 0.5 voxel the best by 0.04 dB at three times the
    cost. The full-quality frames at the finest spacing are measured like the others; they used
    to be served unmeasured, and with a colour threshold per sample were the worst of all."""
    agreeing = [r for r in tried if agreement[r] >= min_agreement_db]
    if not agreeing:
        return finest
    best = max(tried[r] for r in agreeing)
    return max(r for r in agreeing if tried[r] >= best - tolerance_db)
