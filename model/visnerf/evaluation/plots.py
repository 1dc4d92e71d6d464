"""The report's figures as PNG files (matplotlib's object API, no global pyplot state)."""

import io
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap, Normalize
from matplotlib.figure import Figure
from matplotlib.ticker import ScalarFormatter
from PIL import Image

from visnerf.evaluation.colour_difference import legend_colours
from visnerf.evaluation.sweeps import SweepPoint
from visnerf.evaluation.training_curves import TrainingRun

_DPI = 110


def save_figure(fig: Figure, path: Path, dpi: int = _DPI) -> Path:
    """``fig`` as a PNG of 256 adaptive colours: a figure of frames and plots in about 40 % of the
    bytes of its full-colour PNG (the measured frames themselves are written in full colour)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=dpi, format="png")
    buffer.seek(0)
    with Image.open(buffer) as image:
        image.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(path, optimize=True)
    return path




def legend_colormap() -> ListedColormap:
    """The fixed difference legend as a matplotlib colour map."""
    return ListedColormap(legend_colours(np.linspace(0.0, 1.0, 256)), name="visnerf_luv_difference")


def plot_per_frame(path: Path, psnrs: list[float], groups: list[str], ms: list[float]) -> Path:
    """PSNR and render time of every frame in split order, coloured by where it sits in parameter space."""
    fig = Figure(figsize=(8, 4.5), layout="constrained")
    ax_psnr, ax_ms = fig.subplots(2, 1, sharex=True, height_ratios=(2, 1))
    x = np.arange(len(psnrs))
    values = np.asarray([p if np.isfinite(p) else np.nan for p in psnrs])
    for name in dict.fromkeys(groups):
        mask = np.asarray([g == name for g in groups])
        ax_psnr.scatter(x[mask], values[mask], s=10, label=name)
    ax_psnr.set_ylabel("PSNR (dB)")
    ax_psnr.legend(fontsize="small", loc="best")
    ax_psnr.grid(alpha=0.3)
    ax_ms.plot(x, ms, lw=1, color="0.3")
    ax_ms.set_ylabel("render ms")
    ax_ms.set_xlabel("frame (split order)")
    ax_ms.grid(alpha=0.3)
    return save_figure(fig, path)


def plot_render_sweep(path: Path, points: list[SweepPoint]) -> Path:
    """PSNR against milliseconds per frame for every render setting, the Pareto front joined."""
    fig = Figure(figsize=(7, 4.5), layout="constrained")
    ax = fig.subplots()
    for group in dict.fromkeys(p.group for p in points):
        sel = [p for p in points if p.group == group]
        ax.scatter([p.ms_median for p in sel], [p.psnr for p in sel], s=28, label=group, zorder=3)
    front = sorted((p for p in points if p.on_front), key=lambda p: p.ms_median)
    ax.plot([p.ms_median for p in front], [p.psnr for p in front], color="k", lw=1, ls="--",
            label="Pareto front", zorder=2)
    for p in points:
        if p.on_front or p.group == "baseline":  # the others are in the report's table
            ax.annotate(p.name, (p.ms_median, p.psnr), fontsize=7, xytext=(4, 4), textcoords="offset points")
    times = [p.ms_median for p in points]
    if min(times) > 0 and max(times) / min(times) > 8.0:
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.set_xlabel("milliseconds per frame (median)")
    ax.set_ylabel("PSNR (dB)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize="small")
    return save_figure(fig, path)


def plot_training_curves(path: Path, runs: list[TrainingRun]) -> Path:
    """Validation PSNR against training time (minutes) for one or several runs."""
    fig = Figure(figsize=(7, 4.5), layout="constrained")
    ax = fig.subplots()
    for run in runs:
        minutes = [p.train_seconds / 60.0 for p in run.points]
        label = run.name if run.metric == "val_psnr" else f"{run.name} (training PSNR: nothing held out)"
        ax.plot(minutes, [p.psnr for p in run.points], marker="o", ms=3,
                ls="-" if run.metric == "val_psnr" else ":", label=label)
    ax.set_xlabel("training time (minutes, validation excluded)")
    ax.set_ylabel("validation PSNR (dB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    return save_figure(fig, path)


def plot_difference(
    path: Path, synth: np.ndarray, truth: np.ndarray, delta: np.ndarray, scale_max: int | float, title: str
) -> Path:
    """Synthesized | ground truth | CIELUV difference with the fixed colour bar."""
    fig = Figure(figsize=(9, 3.4), layout="constrained")
    axes = fig.subplots(1, 3)
    axes[0].imshow(synth)
    axes[0].set_title("synthesized", fontsize=9)
    axes[1].imshow(truth)
    axes[1].set_title("ground truth", fontsize=9)
    image = axes[2].imshow(delta, cmap=legend_colormap(), norm=Normalize(0.0, scale_max), interpolation="nearest")
    axes[2].set_title("difference (CIELUV ΔE*uv)", fontsize=9)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(image, ax=axes[2], fraction=0.046, extend="max", label="ΔE*uv")
    fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)


def plot_legend(path: Path, scale_max: int | float) -> Path:
    """The difference legend alone."""
    fig = Figure(figsize=(5, 0.9), layout="constrained")
    ax = fig.subplots()
    ax.imshow(np.linspace(0.0, scale_max, 256)[None], cmap=legend_colormap(), aspect="auto",
              extent=(0.0, scale_max, 0.0, 1.0), norm=Normalize(0.0, scale_max))
    ax.set_yticks([])
    ax.set_xlabel(f"CIELUV ΔE*uv (values above {scale_max:g} take the top colour)")
    return save_figure(fig, path)
