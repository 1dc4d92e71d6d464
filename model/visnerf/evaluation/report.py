"""Write an evaluation as files: CSV and JSON data, PNG images and plots, a Markdown report.

Layout of the report folder:

    report.md                 the report, linking everything below
    summary.json              every figure of the report
    frames.csv                per frame: parameters, placement, PSNR, SSIM, LPIPS, Delta E, render ms
    render_sweep.csv          PSNR / SSIM / ms per frame of each render setting, Pareto front marked
    training_curves.csv       validation PSNR against training time, per run
    figures/*.png             per-frame plot, render sweep, training curves, difference figures, legend
    images/frame_N_{synth,truth,diff}.png   the difference examples at full resolution
"""

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
from PIL import Image

from visnerf.evaluation import plots
from visnerf.evaluation.colour_difference import colourize_difference
from visnerf.evaluation.evaluate import EvalConfig, EvalResult
from visnerf.evaluation.markdown import render_markdown
from visnerf.evaluation.summary import aggregate, group_label, json_safe, parameter_space_groups


def _write_csv(path: Path, rows: list[dict]) -> Path:
    keys = list(dict.fromkeys(k for row in rows for k in row)) or ["empty"]
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
    return path


def _frame_rows(result: EvalResult) -> list[dict]:
    names = [a.name for a in result.meta.param_axes]
    rows = []
    for r in result.frames:
        rows.append({
            "frame": r.index, "file": r.file, **dict(zip(names, r.params, strict=True)),
            "at_training_values": r.placement.at_training_values, "offset_spacings": round(r.placement.offset, 4),
            "moving_params": r.placement.n_moving, "motion": r.placement.motion,
            "psnr": r.psnr, "ssim": r.ssim, "lpips": "" if r.lpips is None else r.lpips,
            "delta_e_mean": r.delta_e_mean, "render_ms": r.ms,
        })  # fmt: skip
    return rows


def _differences(result: EvalResult, out: Path, scale_max: float) -> list[dict]:
    entries = []
    plots.plot_legend(out / "figures" / "difference_legend.png", scale_max)
    for ex in result.differences:
        stem = f"frame_{ex.index:04d}"
        files = {kind: f"images/{stem}_{kind}.png" for kind in ("synth", "truth", "diff")}
        Image.fromarray(ex.synth).save(out / files["synth"])
        Image.fromarray(ex.truth).save(out / files["truth"])
        Image.fromarray(colourize_difference(ex.delta, scale_max)).save(out / files["diff"])
        figure = f"figures/difference_{stem}.png"
        plots.plot_difference(out / figure, ex.synth, ex.truth, ex.delta, scale_max,
                              f"frame {ex.index} ({ex.reason}): PSNR {ex.psnr:.2f} dB")
        entries.append({
            "frame": ex.index, "reason": ex.reason, "psnr": ex.psnr, "delta_e_mean": float(ex.delta.mean()),
            "delta_e_p95": float(np.percentile(ex.delta, 95)), "delta_e_max": float(ex.delta.max()),
            "images": files, "figure": figure,
        })  # fmt: skip
    return entries


def _training(result: EvalResult, out: Path) -> dict:
    rows = [
        {"run": run.name, "source": str(run.source), "metric": run.metric, "iteration": p.iteration,
         "train_seconds": p.train_seconds, "wall_seconds": p.wall_seconds, "psnr": p.psnr,
         "ssim": "" if p.ssim is None else p.ssim}
        for run in result.training_runs for p in run.points
    ]  # fmt: skip
    section: dict = {"note": result.training_note, "runs": [], "figure": None, "data": None}
    if not result.training_runs:
        return section
    section["data"] = _write_csv(out / "training_curves.csv", rows).name
    section["figure"] = "figures/training_curves.png"
    plots.plot_training_curves(out / section["figure"], list(result.training_runs))
    for run in result.training_runs:
        last = run.points[-1]
        section["runs"].append({
            "name": run.name, "source": str(run.source), "metric": run.metric, "points": len(run.points),
            "final_psnr": last.psnr, "final_ssim": last.ssim, "train_minutes": last.train_seconds / 60.0,
            "best_psnr": max(p.psnr for p in run.points),
        })  # fmt: skip
    return section


def _sweep(result: EvalResult, out: Path) -> dict:
    if not result.sweep:
        return {"points": [], "figure": None, "data": None}
    rows = [dataclasses.asdict(p) for p in result.sweep]
    figure = "figures/render_sweep.png"
    plots.plot_render_sweep(out / figure, list(result.sweep))
    return {"points": rows, "figure": figure, "data": _write_csv(out / "render_sweep.csv", rows).name}


def _remove_earlier_examples(out: Path) -> None:
    """Delete the difference examples a report written earlier into ``out`` left (their frames
    are chosen by this evaluation's errors, so another run names other files); only files of the
    names this writer gives them."""
    for path in [*(out / "figures").glob("difference_frame_*.png"), *(out / "images").glob("frame_*_*.png")]:
        path.unlink()


def build_summary(result: EvalResult, cfg: EvalConfig, out: Path) -> dict:
    """Write the data files and figures; return the summary document."""
    (out / "figures").mkdir(parents=True, exist_ok=True)
    (out / "images").mkdir(parents=True, exist_ok=True)
    _remove_earlier_examples(out)
    meta = result.meta
    frames = list(result.frames)
    k = len(meta.param_axes)
    _write_csv(out / "frames.csv", _frame_rows(result))
    plots.plot_per_frame(out / "figures" / "psnr_per_frame.png", [r.psnr for r in frames],
                         [group_label(r, k) for r in frames], [r.ms for r in frames])
    overall = aggregate(frames)
    return {
        "checkpoint": str(result.checkpoint), "data": str(result.data), "split": result.split,
        "quality": result.quality, "device": result.device, "torch_threads": result.torch_threads,
        "model_mb": result.model_mb,
        "scene": {"title": meta.title, "kind": meta.kind, "K": k,
                  "param_axes": [{"name": a.name, "min": a.min, "max": a.max, "values": list(a.values)}
                                 for a in meta.param_axes]},
        "provenance": meta.provenance.to_dict(),
        "metrics": {**overall, "lpips_note": result.lpips_note,
                    "note": "means over frames; SSIM: scikit-image, Gaussian window, data range 1, colour; "
                            "render ms: median after one untimed warm-up, 8-bit output"},
        "parameter_space": {
            "groups": parameter_space_groups(frames, k),
            "note": "static scene: no parameter space, every frame counts as at training values" if k == 0
            else "motion is read along the split's frame order (only reported for K >= 2)",
        },
        "differences": {"space": "CIELUV (D65, 2 degree observer)", "metric": "Delta E*uv per pixel",
                        "scale_max": cfg.difference_scale_max, "legend": "figures/difference_legend.png",
                        "frames": _differences(result, out, cfg.difference_scale_max)},
        "render_sweep": {**_sweep(result, out), "frames": cfg.sweep.n_frames if result.sweep else 0},
        "training": _training(result, out),
        "figures": {"per_frame": "figures/psnr_per_frame.png"},
        "data_files": {"frames": "frames.csv"},
    }  # fmt: skip


def write_report(result: EvalResult, cfg: EvalConfig, out_dir: str | Path) -> dict:
    """Write the whole report folder; returns the (JSON-safe) summary."""
    out = Path(out_dir)
    summary = json_safe(build_summary(result, cfg, out))
    assert isinstance(summary, dict)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False))
    (out / "report.md").write_text(render_markdown(summary))
    return summary
