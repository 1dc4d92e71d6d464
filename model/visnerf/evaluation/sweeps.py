"""Error against render time: sweep the settings that trade one for the other, mark the Pareto front.

The sweep varies one setting at a time around the checkpoint's full-quality settings (sample step,
empty-space skipping, early ray termination and its threshold, image scale) and adds the server's
preview quality. Each variant renders the same frames; PSNR and SSIM are their means, the time their
median.
"""

import dataclasses
from dataclasses import dataclass

import numpy as np
from jaxtyping import Float, UInt8
from torch import Tensor

from visnerf.data.cameras import Intrinsics
from visnerf.evaluation.frames import render_frame
from visnerf.evaluation.metrics import psnr, ssim
from visnerf.rendering.render_settings import RenderSettings
from visnerf.representation.field import VisNerfField


@dataclass(frozen=True)
class SweepConfig:
    """Which render settings the time/quality sweep tries."""

    enabled: bool = True
    n_frames: int = 4
    """Frames of the split rendered per variant (evenly chosen)."""
    step_ratios: tuple[float, ...] = (0.25, 0.5, 1.0, 2.0)
    """Sample steps in voxel sizes (the checkpoint's own is the baseline)."""
    early_stop_eps: tuple[float, ...] = (1e-3, 1e-2, 5e-2)
    """Transmittance thresholds at which rays stop."""
    resolution_scales: tuple[float, ...] = (0.5, 0.25)
    """Render at this fraction of the size, then upsample."""
    without_empty_space_skipping: bool = True
    without_early_termination: bool = True
    preview: bool = True
    """Include the server's preview quality."""


@dataclass(frozen=True)
class SweepVariant:
    """One point of the sweep before it is measured."""

    name: str
    group: str
    """What it varies: baseline, step, skipping, termination, scale or quality."""
    settings: RenderSettings


@dataclass(frozen=True)
class SweepPoint:
    """A measured variant."""

    name: str
    group: str
    step_ratio: float
    use_occupancy: bool
    early_termination: bool
    early_stop_eps: float
    resolution_scale: float
    psnr: float
    ssim: float
    ms_median: float
    ms_mean: float
    on_front: bool = False
    """No other variant is both at least as fast and at least as accurate (one of them strictly)."""


def sweep_variants(
    full: RenderSettings, preview: RenderSettings, cfg: SweepConfig, has_occupancy: bool
) -> list[SweepVariant]:
    """The baseline (``full``) and one variant per swept value; duplicates of the baseline dropped."""
    replace = dataclasses.replace
    out = [SweepVariant("full (checkpoint settings)", "baseline", full)]
    for ratio in cfg.step_ratios:
        if ratio != full.step_ratio:
            out.append(SweepVariant(f"step {ratio:g} voxel", "step", replace(full, step_ratio=float(ratio))))
    if cfg.without_empty_space_skipping and has_occupancy:
        out.append(SweepVariant("no empty-space skipping", "skipping", replace(full, use_occupancy=False)))
    if cfg.without_early_termination:
        out.append(SweepVariant("no early termination", "termination", replace(full, early_termination=False)))
    for eps in cfg.early_stop_eps:
        if eps != full.early_stop_eps:
            out.append(SweepVariant(f"stop at T < {eps:g}", "termination", replace(full, early_stop_eps=float(eps))))
    for scale in cfg.resolution_scales:
        if scale != full.resolution_scale:
            out.append(SweepVariant(f"scale {scale:g}", "scale", replace(full, resolution_scale=float(scale))))
    if cfg.preview:
        out.append(SweepVariant("preview quality", "quality", preview))
    return out


def pareto_front(ms: list[float], quality: list[float]) -> list[bool]:
    """Whether each point is on the front: lower time and higher quality are better."""
    front = []
    for i, (t_i, q_i) in enumerate(zip(ms, quality, strict=True)):
        dominated = any(
            t_j <= t_i and q_j >= q_i and (t_j < t_i or q_j > q_i)
            for j, (t_j, q_j) in enumerate(zip(ms, quality, strict=True))
            if j != i
        )
        front.append(not dominated)
    return front


def run_sweep(
    field: VisNerfField,
    variants: list[SweepVariant],
    images: UInt8[Tensor, "n h w 3"],
    c2w: Float[Tensor, "n 4 4"],
    intrinsics: Intrinsics,
    params: Float[Tensor, "n k"],
) -> list[SweepPoint]:
    """Render every frame with every variant (after one untimed warm-up render) and measure it."""
    if images.shape[0] == 0:
        return []
    render_frame(field, c2w[0], intrinsics, params[0], variants[0].settings)  # warm-up, untimed
    rows = []
    for variant in variants:
        psnrs, ssims, times = [], [], []
        for i in range(images.shape[0]):
            frame = render_frame(field, c2w[i], intrinsics, params[i], variant.settings)
            truth = images[i].numpy().astype(np.float32) / 255.0
            psnrs.append(psnr(frame.rgb, truth))
            ssims.append(ssim(frame.rgb, truth))
            times.append(frame.ms)
        s = variant.settings
        rows.append(
            SweepPoint(
                name=variant.name, group=variant.group, step_ratio=float(s.step_ratio),
                use_occupancy=bool(s.use_occupancy and field.occupancy is not None),
                early_termination=bool(s.early_termination), early_stop_eps=float(s.early_stop_eps),
                resolution_scale=float(s.resolution_scale), psnr=float(np.mean(psnrs)),
                ssim=float(np.mean(ssims)), ms_median=float(np.median(times)), ms_mean=float(np.mean(times)),
            )
        )  # fmt: skip
    front = pareto_front([r.ms_median for r in rows], [r.psnr for r in rows])
    return [dataclasses.replace(r, on_front=f) for r, f in zip(rows, front, strict=True)]


def sweep_frame_indices(n_frames: int, count: int) -> list[int]:
    """``count`` evenly spread frame indices of ``n_frames``."""
    if n_frames == 0 or count <= 0:
        return []
    return sorted({int(i) for i in np.linspace(0, n_frames - 1, min(count, n_frames)).round()})

