"""Train on shared/data/nyx under a wall-clock budget and record what it reaches.

Held out for validation (``--holdout``), each kind reported on its own:

- views: views 5, 17, 29 and 40 of the icosphere at every setting (new cameras; Nyx has ground
  truth only at its 42 icosphere views, so these are the only new views there are to measure);
- settings: four whole parameter settings, new combinations of values every axis has in training;
- middle value (``--holdout middle``, the default): every setting at the middle sampled value of
  one axis (``--middle-axis``; by default the first axis with an odd count of values: on Nyx p0,
  which is OmM (its transforms name no parameters), at 0.1375: 15 of the 45 settings), so
  training has only the values on either side of it and these frames measure the model between
  sampled values, which the hidden test path (181 views, parameters moving between the training
  values) does and the other two kinds do not.

``middle`` is the default because it measures what the test measures, values between samples.
``--holdout standard`` is the hold-out of the runs before this option (views and settings only:
1558 training frames, 332 held out), kept so that the history stays comparable; ``middle`` trains
on 1064 frames (28 settings of 38 views) and holds out 826, so its figures are not comparable with
``standard`` ones (other training frames, other held-out frames). A frame held out on several
counts is reported under the newest: a middle value over a setting over a view (two of the four
settings lie at OmM 0.1375, so ``middle`` reports two settings). `visnerf train` holds out the
same with ``--holdout-views 5,17,29,40 --holdout-params ... --holdout-value p0=0.1375``.

Records validation PSNR/SSIM per kind against training time (each validation renders the same
``NYX_VALIDATION_FRAMES_PER_KIND`` frames of each kind), iterations per second, peak RSS,
checkpoint size and seconds per 256x256 frame; the final evaluation renders ``--eval-frames``
held-out frames, shared evenly among the kinds.

    .venv/bin/python bench/nyx_train.py --minutes 60

It trains with the product's recipe, as `visnerf train ../shared/data/nyx --time-budget 60` does
(``training.recipe`` chooses the grid and the carving from the data); what is its own is the
hold-out, the validation frames and the report. Like `visnerf train` it keeps its run state
beside the checkpoint every ``TrainConfig.checkpoint_every_s`` (the report gives their count and
cost) and deletes it at the end. Writes the checkpoint to runs/nyx.safetensors (``--out``) and nyx_train.json, .md and .png to
bench/results/nyx_train_nyx/ (``--results``; by default named after the checkpoint). It refuses,
before training, to write over a checkpoint or a report that exists (``--force`` does).

Runs started together on one machine (``--threads 1`` each) share its noise, which runs from
different sessions do not. ``--side-by-side FOLDER --run SUB=LABEL --run SUB=LABEL --title T``
reads the reports of such runs from FOLDER/SUB and writes FOLDER/README.md: the commands, the final
figures in columns (per held-out kind where a run has them; reports from before the kinds give
views and settings) and the validation PSNR at each validation with its difference from the first
run (``--about`` adds a paragraph on what they share and differ in); it trains nothing.

    .venv/bin/python bench/nyx_train.py --side-by-side bench/results/nyx_fused_hour \\
        --run fused="the fused step" --run before="the tree before" --title "Nyx, side by side"
"""

import visnerf  # noqa: F401  (before torch: it sets the OpenMP wait policy that torch reads once)

# isort: split
import argparse
import json
import math
import os
import resource
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from bench_common import (
    HOLDOUT_PROTOCOLS,
    ROOT,
    cpu_description,
    evenly_spaced,
    fmt,
    holdout_for,
    middle_holdout,
    render_frame,
    write_json,
)

from visnerf.arg_types import positive_float, positive_int
from visnerf.config import FieldConfig, HoldoutConfig, TrainConfig
from visnerf.data.datasets import load_dataset
from visnerf.data.holdout import HELD_OUT_KINDS, held_out_kind, split_holdout
from visnerf.data.scene import SceneData
from visnerf.evaluation.colour_difference import luv_difference
from visnerf.evaluation.evaluate import EvalConfig
from visnerf.evaluation.metrics import psnr, ssim
from visnerf.evaluation.plots import plot_difference
from visnerf.inference import load_scene
from visnerf.runtime import pick_device
from visnerf.training.recipe import recipe_trainer
from visnerf.training.record import validate
from visnerf.training.run_state import run_state_path

NYX_VALIDATION_FRAMES_PER_KIND = 3
"""Held-out frames of each kind that each periodic validation renders, evenly chosen among that
kind's frames, the same each time (the final evaluation renders ``--eval-frames``)."""
EARLIER_VALIDATION = "6 held-out frames evenly chosen over all of them"
"""What the periodic validation of reports from before the per-kind validation rendered."""
KIND_WORDS = {"view": "held-out views", "setting": "held-out settings", "axis_value": "the held-out middle value"}
"""The kinds of ``visnerf.data.holdout.HELD_OUT_KINDS`` in a report's words."""


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def frames_by_kind(val: SceneData, holdout: HoldoutConfig) -> dict[str, list[int]]:
    """The validation frames of each held-out kind (``held_out_kind``), kinds with no frame left out."""
    kinds = held_out_kind(val, holdout)
    if None in kinds:
        raise ValueError("a validation frame matches no rule of the hold-out: were they split by another one?")
    by_kind = {k: [i for i, x in enumerate(kinds) if x == k] for k in HELD_OUT_KINDS}
    return {k: frames for k, frames in by_kind.items() if frames}


def chosen(frames: list[int], count: int) -> list[int]:
    """``count`` of ``frames`` (fewer if there are fewer), evenly spread over them."""
    return [frames[j] for j in evenly_spaced(len(frames), count)]


def kind_label(kind: str, holdout: dict[str, Any] | None) -> str:
    """A kind in a report's words; the middle value with its axis and value where the record has them."""
    if kind == "axis_value" and holdout and holdout.get("axis_values"):
        values = ", ".join(f"{name} = {value:g}" for name, value in
                           zip(holdout.get("axis_names", []), (v for _, v in holdout["axis_values"]), strict=False))
        return f"the held-out middle value ({values})" if values else KIND_WORDS[kind]
    return KIND_WORDS[kind]


def final_eval(ckpt: Path, val: SceneData, by_kind: dict[str, list[int]], n_frames: int,
               figure: Path | None = None, device: torch.device | None = None) -> dict:
    """Render ``n_frames`` held-out frames, shared evenly among the kinds of ``by_kind`` and evenly
    chosen within each, through the public inference API; with ``figure``, save the frame of median
    PSNR beside its ground truth and their CIELUV difference. The mean is over all rendered frames
    (each kind as many as its share, where it has that many)."""
    scene = load_scene(ckpt, device or torch.device("cpu"))
    per_kind = math.ceil(n_frames / len(by_kind))
    rows = []
    for kind, frames in by_kind.items():
        for i in chosen(frames, per_kind):
            t0 = time.perf_counter()
            pred, gt = render_frame(scene, val, i, 256, 256)
            seconds = time.perf_counter() - t0
            rows.append({"frame": int(i), "psnr": psnr(pred, gt), "ssim": ssim(pred, gt), "seconds": seconds,
                         "held_out": kind, "images": (pred, gt)})
    if figure is not None:
        median = sorted(rows, key=lambda r: r["psnr"])[len(rows) // 2]
        pred, gt = median["images"]
        plot_difference(figure, pred, gt, luv_difference(pred, gt), EvalConfig.difference_scale_max,
                        f"held-out frame {median['frame']} (at {KIND_WORDS[median['held_out']]}), "
                        f"the median of {len(rows)}: {median['psnr']:.2f} dB")
    for r in rows:
        del r["images"]

    def mean(kind: str, metric: str) -> float:
        return float(np.mean([r[metric] for r in rows if r["held_out"] == kind] or [np.nan]))

    return {
        "frames": len(rows),
        "psnr": float(np.mean([r["psnr"] for r in rows])),
        "ssim": float(np.mean([r["ssim"] for r in rows])),
        "kinds": {kind: {"frames": sum(r["held_out"] == kind for r in rows), "of": len(frames),
                         "psnr": mean(kind, "psnr"), "ssim": mean(kind, "ssim")} for kind, frames in by_kind.items()},
        # the names of the reports before the kinds, which --side-by-side reads
        "psnr_held_out_settings": mean("setting", "psnr"),
        "psnr_held_out_views": mean("view", "psnr"),
        "psnr_held_out_middle": mean("axis_value", "psnr"),
        "seconds_per_frame_256_median": float(np.median([r["seconds"] for r in rows])),
    }


def final_by_kind(final: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """A report's final PSNR (and SSIM, frames where it has them) per kind; a report from before
    the kinds gives the PSNR at held-out views and settings only."""
    if "kinds" in final:
        return final["kinds"]
    old = {"view": final.get("psnr_held_out_views"), "setting": final.get("psnr_held_out_settings")}
    return {kind: {"psnr": value} for kind, value in old.items() if value is not None}


def kind_cell(figures: dict[str, Any] | None) -> str:
    """"PSNR dB / SSIM (n of N frames)" of one kind, with what the record has; "-" without it."""
    if not figures or figures.get("psnr") is None:
        return "-"
    text = f"{fmt(figures['psnr'], 2)} dB"
    if figures.get("ssim") is not None:
        text += f" / {fmt(figures['ssim'], 3)}"
    if "frames" in figures:
        text += f" ({figures['frames']} of {figures['of']} frames)"
    return text


def log_kinds(log: list[dict[str, Any]]) -> list[str]:
    """The kinds whose validation figures a training log holds, in ``HELD_OUT_KINDS`` order."""
    return [k for k in HELD_OUT_KINDS if any(f"val_psnr_{k}" in row for row in log)]


def holdout_words(holdout: dict[str, Any] | None) -> str:
    """The hold-out of a run, from its record (reports from before the option: the standard one)."""
    if not holdout:
        return "standard (views and settings; recorded before --holdout)"
    parts = [f"views {', '.join(map(str, holdout['views']))} at every setting",
             f"{len(holdout['settings'])} settings"]
    if holdout.get("axis_values"):
        parts.append(kind_label("axis_value", holdout).removeprefix("the held-out ") + " at every setting and view")
    return f"{holdout['protocol']}: " + "; ".join(parts)


def write_report(result: dict, out_dir: Path) -> None:
    write_json(out_dir / "nyx_train.json", result)
    f = result["final"]
    holdout = result.get("holdout")
    kinds = final_by_kind(f)
    counts = result.get("val_frames_by_kind", {})
    lines = [
        "# Nyx training on " + ("this CPU" if result.get("device", "cpu") == "cpu" else result["device"]),
        "",
        f"Command: `{result['command']}`  ",
        f"Machine: {result['machine']}",
        "",
        "| what | value |",
        "| --- | --- |",
        (f"| training budget | {result['budget_minutes']} min, space carving ({result['carve_seconds']} s) included, validation excluded |"
         if result.get("budget_minutes") else
         f"| training budget | {result['budget_iterations']} iterations ({result['train_seconds'] / 60:.1f} min) |"),
        f"| 1-min load average before / after | {result['load_average_before_after'][0]} / {result['load_average_before_after'][1]} |",
        f"| hold-out | {holdout_words(holdout)}: {result['train_frames']} frames trained on, {result['val_frames']} "
        "held out" + (" (" + ", ".join(f"{n} at {KIND_WORDS[k]}" for k, n in counts.items()) + ")" if counts else "") + " |",
        f"| iterations | {result['iterations']} ({result['iterations_per_second']:.2f} it/s) |",
        f"| held-out PSNR / SSIM ({f['frames']} frames, all kinds) | {f['psnr']:.2f} dB / {f['ssim']:.3f} |",
        *[f"| at {kind_label(k, holdout)} | {kind_cell(kinds.get(k))} |" for k in HELD_OUT_KINDS if k in kinds],
        f"| peak RSS | {result['peak_rss_mb']:.0f} MB |",
        f"| checkpoint size | {result['checkpoint_mb']:.2f} MB |",
        f"| run states | {result['run_states']['written']} written (every {result['run_states']['every_s']:g} s, "
        f"{result['run_states']['file_mb']:.0f} MB each), {result['run_states']['seconds']:.1f} s in all |",
        f"| model box (after carving) | {result['box'][0]} to {result['box'][1]}, grid {result['final_resolution']} |",
        f"| recipe | {', '.join(f'{k} {v}' for k, v in result.get('recipe', {}).items())} |",
        f"| full-quality spacing chosen at the end | {result.get('full_spacing')} |",
        *([f"| inference grid | {g['cells']} cells, within the grid training last sampled; rebuilt from the density alone: "
           f"{g['unrestricted_cells']} cells, {g['unrestricted_psnr']:.2f} dB / {g['unrestricted_ssim']:.3f} on the same frames |"]
          if (g := result.get("final_grid")) else []),
        *([f"| parameters saved | their moving average (span {result['recipe']['weight_average_span']:g} of the run): "
           f"{w['average_val_psnr']:.2f} dB on the validation frames against {w['live_val_psnr']:.2f} dB from the last "
           "values, both before the final grid |"]
          if "live_val_psnr" in (w := result["log"][-1] if result.get("log") else {}) else []),
        f"| seconds per 256x256 frame (median) | {f['seconds_per_frame_256_median']:.2f} s |",
        "",
    ]
    logged = log_kinds(result["log"])
    per_kind = result.get("validation_frames_per_kind")
    lines += [
        "Validation PSNR against training time"
        + (f" ({per_kind} frames of each kind, the same at each validation; val PSNR is their mean):"
           if per_kind else ":"),
        "",
        "| train s | iteration | train PSNR | val PSNR | val SSIM | "
        + "".join(f"{KIND_WORDS[k]}: PSNR / SSIM | " for k in logged) + "grid | occupied cells |",
        "|" + " --- |" * (7 + len(logged)),
    ]
    for row in result["log"]:
        by_kind = "".join(f"{fmt(row.get(f'val_psnr_{k}'), 2)} / {fmt(row.get(f'val_ssim_{k}'), 3)} | " for k in logged)
        lines.append(f"| {row['train_seconds']:.0f} | {row['iteration']} | {row['train_psnr']:.2f} | "
                     f"{fmt(row.get('val_psnr'), 2)} | {fmt(row.get('val_ssim'), 3)} | {by_kind}"
                     f"{row.get('resolution', '')} | {row.get('occupied_cells', '')} |")
    lines += ["", "![validation PSNR against training time](nyx_train.png)", "",
              "![the held-out frame of median PSNR](nyx_heldout.png)", ""]
    (out_dir / "nyx_train.md").write_text("\n".join(lines))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6.5, 4))
        log = result["log"]
        minutes = [r["train_seconds"] / 60 for r in log]
        for k in logged:
            ax.plot(minutes, [r.get(f"val_psnr_{k}", np.nan) for r in log], "o-", ms=3, label=kind_label(k, holdout))
        ax.plot(minutes, [r.get("val_psnr", np.nan) for r in log], "-" if logged else "o-", color="black",
                lw=0.8 if logged else 1.5, label="held-out, all kinds" if logged else "held-out")
        ax.plot(minutes, [r["train_psnr"] for r in log], "--", color="gray", label="train (EMA)")
        ax.axhline(28.0, color="gray", lw=0.8, ls=":", label="target 28 dB")
        ax.set_xlabel("training minutes" + (" (2-core CPU)" if result.get("device", "cpu") == "cpu" else ""))
        ax.set_ylabel("PSNR (dB)")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(out_dir / "nyx_train.png", dpi=110)
        plt.close(fig)
    except ImportError:
        pass


# --- the report of runs made side by side ---------------------------------------------------


def parse_run(text: str) -> tuple[str, str]:
    """``SUBFOLDER=LABEL`` (or ``SUBFOLDER``, labelled by itself) as (subfolder, label)."""
    folder, _, label = text.partition("=")
    if not folder or "/" in folder or folder in (".", ".."):
        raise argparse.ArgumentTypeError(f"expected SUBFOLDER=LABEL with a plain subfolder name, got {text!r}")
    return folder, label or folder


def load_run(folder: Path) -> dict[str, Any]:
    path = folder / "nyx_train.json"
    if not path.is_file():
        raise SystemExit(f"error: {path} does not exist: is {folder} a finished bench/nyx_train.py run?")
    with open(path) as f:
        result = json.load(f)
    missing = [k for k in ("command", "final", "log", "iterations", "iterations_per_second", "peak_rss_mb")
               if k not in result]
    if missing:
        raise SystemExit(f"error: {path} lacks {', '.join(missing)}: not a bench/nyx_train.py report")
    return result


def validation_rows(result: dict[str, Any]) -> list[dict[str, Any]]:
    return [row for row in result["log"] if row.get("val_psnr") is not None]


def spacing_chosen(note: str | None) -> str:
    """The spacing from the trainer's note ("full-quality spacing 1 voxel (exhaustive ...)")."""
    if not note:
        return "none"
    return note.split(" (")[0].removeprefix("full-quality spacing ")


def summary_table(labels: list[str], runs: list[dict[str, Any]]) -> list[str]:
    def row(name: str, cell) -> str:
        return f"| {name} | " + " | ".join(cell(r) for r in runs) + " |"

    kinds = [k for k in HELD_OUT_KINDS if any(k in final_by_kind(r["final"]) for r in runs)]
    return [
        "| | " + " | ".join(labels) + " |",
        "| --- | " + " | ".join("---" for _ in runs) + " |",
        row("hold-out", lambda r: holdout_words(r.get("holdout"))),
        row("held-out PSNR / SSIM (all kinds)",
            lambda r: f"{r['final']['psnr']:.2f} dB / {r['final']['ssim']:.3f} ({r['final']['frames']} frames)"),
        *[row(f"at {KIND_WORDS[k]}", lambda r, k=k: kind_cell(final_by_kind(r["final"]).get(k))) for k in kinds],
        row("iterations", lambda r: f"{r['iterations']} ({r['iterations_per_second']:.2f} it/s)"),
        row("peak RSS", lambda r: f"{r['peak_rss_mb']:.0f} MB"),
        row("checkpoint", lambda r: f"{r.get('checkpoint_mb', float('nan')):.2f} MB"),
        row("full-quality spacing chosen", lambda r: spacing_chosen(r.get("full_spacing"))),
        row("seconds per 256x256 frame (median)", lambda r: f"{r['final']['seconds_per_frame_256_median']:.2f}"),
    ]


def validation_table(labels: list[str], runs: list[dict[str, Any]]) -> list[str]:
    """One line per validation, matched by order: the runs validate every ``--validate-every``
    seconds of training, but a step or a milestone can carry one past that; the first column gives
    each run's own training seconds. Where some run logged figures per held-out kind, each run has
    a column of them (a dash for a run without)."""
    rows = [validation_rows(r) for r in runs]
    kinds = [k for k in HELD_OUT_KINDS if any(k in log_kinds(r["log"]) for r in runs)]
    per_run = 3 if kinds else 2
    words = " / ".join(KIND_WORDS[k].removeprefix("the ").removeprefix("held-out ") for k in kinds)
    head = "| train s | " + " | ".join(f"iterations ({lab}) | val PSNR ({lab})"
                                       + (f" | {words} ({lab})" if kinds else "") for lab in labels)
    head += "".join(f" | {labels[0]} minus {lab}" for lab in labels[1:]) + " |"
    lines = [head, "|" + " --- |" * (1 + per_run * len(runs) + len(runs) - 1)]
    for i in range(min(len(r) for r in rows)):
        at = [r[i] for r in rows]
        cells = [" / ".join(f"{a['train_seconds']:.0f}" for a in at)]
        for a in at:
            cells += [str(a["iteration"]), f"{a['val_psnr']:.2f}"]
            if kinds:  # a dash for a run without figures per kind
                logged = any(f"val_psnr_{k}" in a for k in kinds)
                cells.append(" / ".join(fmt(a.get(f"val_psnr_{k}"), 2) for k in kinds) if logged else "-")
        cells += [f"{at[0]['val_psnr'] - a['val_psnr']:+.2f} dB" for a in at[1:]]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def validation_words(result: dict[str, Any]) -> str:
    per_kind = result.get("validation_frames_per_kind")
    if per_kind is None:
        return EARLIER_VALIDATION
    return f"{per_kind} frames of each held-out kind, their mean"


def report(folder: Path, runs: list[tuple[str, str]], title: str, about: str) -> str:
    results = [load_run(folder / sub) for sub, _ in runs]
    labels = [label for _, label in runs]
    lines = [f"# {title}", "", "The runs, started together on this machine:", ""]
    lines += [f"    {r['command']}" for r in results]
    lines += ["", "Machine: " + " / ".join(sorted({str(r.get("machine")) for r in results})) + "."]
    lines += ["", "Reports written at " + " / ".join(str(r.get("date")) for r in results)
              + "; 1-min load average before / after each: "
              + ", ".join(f"{r['load_average_before_after'][0]} / {r['load_average_before_after'][1]}"
                          for r in results if "load_average_before_after" in r)
              + ". Each run's own report: " + ", ".join(f"{sub}/nyx_train.md" for sub, _ in runs) + "."]
    if about:
        lines += ["", about]
    if len({holdout_words(r.get("holdout")) for r in results}) > 1:
        lines += ["", "The runs held out different frames (the hold-out row): their held-out figures are not "
                  "comparable with each other."]
    validations = sorted({validation_words(r) for r in results})
    lines += ["", *summary_table(labels, results), "",
              f"Validation PSNR (bench/nyx_train.py validates on {' / '.join(validations)}) against training time:",
              "", *validation_table(labels, results), ""]
    return "\n".join(lines)


def nyx_holdout(scene: SceneData, protocol: str, middle_axis: str | None) -> tuple[HoldoutConfig, dict[str, Any]]:
    """The hold-out of ``--holdout`` and its record (``protocol``, views, settings, axis values
    and their axis names)."""
    holdout = middle_holdout(scene, middle_axis) if protocol == "middle" else holdout_for(scene)
    record = {"protocol": protocol, "views": list(holdout.views), "settings": [list(s) for s in holdout.settings],
              "axis_values": [[axis, value] for axis, value in holdout.axis_values],
              "axis_names": [scene.param_axes[axis].name for axis, _ in holdout.axis_values]}
    return holdout, record


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "nyx"))
    ap.add_argument("--minutes", type=positive_float, default=60.0)
    ap.add_argument("--iterations", type=positive_int, default=None,
                    help="schedule by this many iterations instead of --minutes (a GPU run, to see "
                         "what more iterations of the same recipe reach)")
    ap.add_argument("--device", default="cpu", help="cpu (default), cuda or auto")
    ap.add_argument("--holdout", choices=HOLDOUT_PROTOCOLS, default="middle",
                    help="middle (default): held-out views, settings and the middle value of one axis; standard: "
                         "views and settings, the hold-out of the runs before this option")
    ap.add_argument("--middle-axis", default=None, metavar="NAME",
                    help="--holdout middle: the axis whose middle value is held out (default: the first with an "
                         "odd count of values; p0, OmM, on Nyx)")
    ap.add_argument("--validate-every", type=positive_float, default=300.0, help="seconds of training")
    ap.add_argument("--eval-frames", type=positive_int, default=24,
                    help="held-out frames of the final evaluation, shared evenly among the held-out kinds (default 24)")
    ap.add_argument("--threads", type=positive_int, default=None, help="torch threads (default: all cores)")
    ap.add_argument("--figure-only", metavar="CKPT", default=None,
                    help="only render the held-out figure and figures of this checkpoint")
    ap.add_argument("--out", default=str(ROOT / "runs" / "nyx.safetensors"))
    ap.add_argument("--results", default=None,
                    help="folder of the report (default bench/results/nyx_train_<stem of --out>)")
    ap.add_argument("--force", action="store_true", help="write over an existing --out and report")
    ap.add_argument("--side-by-side", metavar="FOLDER", type=Path, default=None,
                    help="only write FOLDER/README.md, the report of the runs named by --run (trains nothing)")
    ap.add_argument("--run", type=parse_run, action="append", default=[], metavar="SUBFOLDER=LABEL",
                    help="--side-by-side: a run's result folder within FOLDER and its label (twice or more; "
                         "the first is the reference)")
    ap.add_argument("--title", default=None, help="--side-by-side: the report's title")
    ap.add_argument("--about", default="", help="--side-by-side: a paragraph on what the runs share and differ in")
    args = ap.parse_args()
    if args.side_by_side is not None:
        if len(args.run) < 2 or not args.title:
            ap.error("--side-by-side needs --title and at least two --run")
        text = report(args.side_by_side, args.run, args.title, args.about)
        (args.side_by_side / "README.md").write_text(text)
        print(text)
        return 0
    if args.middle_axis is not None and args.holdout != "middle":
        ap.error("--middle-axis goes with --holdout middle")
    if args.results is None:
        args.results = str(ROOT / "bench" / "results" / f"nyx_train_{Path(args.out).stem}")
    if not args.figure_only and not args.force:
        taken = [p for p in (Path(args.out), Path(args.results) / "nyx_train.json") if p.exists()]
        if taken:  # an hour of training must not end by writing over an earlier run
            ap.error(f"{' and '.join(map(str, taken))} already exist{'s' if len(taken) == 1 else ''}: "
                     "pass another --out / --results, or --force")

    device = pick_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    t0 = time.perf_counter()
    scene = load_dataset(args.data)
    load_s = time.perf_counter() - t0
    rss_after_load = peak_rss_mb()
    try:
        holdout, holdout_record = nyx_holdout(scene, args.holdout, args.middle_axis)
        train, val = split_holdout(scene, holdout)
    except ValueError as exc:
        ap.error(f"{args.data}: {exc}")
    del scene
    if val is None:
        ap.error(f"{args.data}: the hold-out {holdout} matches no frame")
    by_kind = frames_by_kind(val, holdout)
    if args.figure_only:
        Path(args.results).mkdir(parents=True, exist_ok=True)
        print(json.dumps(final_eval(Path(args.figure_only), val, by_kind, args.eval_frames,
                                    Path(args.results) / "nyx_heldout.png")))
        return 0
    # Each periodic validation renders the same few frames of each kind: the trainer validates on all
    # of them (val PSNR / SSIM, and they choose the full-quality spacing at the end), and the callback
    # adds each kind's own figures to the log row.
    checked = {kind: chosen(frames, NYX_VALIDATION_FRAMES_PER_KIND) for kind, frames in by_kind.items()}
    val_checked = val.subset(torch.tensor([i for frames in checked.values() for i in frames]))
    kind_frames = {kind: val.subset(torch.tensor(frames)) for kind, frames in checked.items()}
    by_iterations = args.iterations is not None
    # The product's recipe (what `visnerf train` runs); only the budget and the validation are this bench's.
    base = TrainConfig(iterations=args.iterations,
                       time_budget_s=None if by_iterations else args.minutes * 60,
                       validate_every_s=args.validate_every, validate_max_images=val_checked.n_frames)
    trainer = recipe_trainer(train, val_checked, base, FieldConfig(), device)
    cfg = trainer.cfg

    def per_kind(row: dict) -> None:  # outside the training time, as the trainer's own validation
        for kind, frames in kind_frames.items():
            figures = validate(trainer.field, frames, trainer.render_cfg, frames.n_frames)
            row[f"val_psnr_{kind}"] = round(figures["val_psnr"], 4)
            row[f"val_ssim_{kind}"] = round(figures["val_ssim"], 4)
        print(json.dumps(row), flush=True)

    state_path = run_state_path(args.out)  # written every checkpoint_every_s, as `visnerf train` does
    trainer.run(progress_bar=sys.stderr.isatty(), on_validate=per_kind, state_path=state_path)
    ckpt = trainer.save(args.out, dataset="shared/data/nyx")
    state_mb = state_path.stat().st_size / 1e6
    state_path.unlink()
    out_dir = Path(args.results)
    out_dir.mkdir(parents=True, exist_ok=True)
    final = final_eval(ckpt, val, by_kind, args.eval_frames, out_dir / "nyx_heldout.png", device)
    # The same trained field with the inference grid the trainer built before finish_occupancy:
    # the density's occupancy now, not limited to the cells training last sampled.
    kept = trainer.field.occupancy
    trainer.update_occupancy(shrink=False)
    other = trainer.save(Path(args.out).with_name(Path(args.out).stem + "_unrestricted.safetensors"), dataset="shared/data/nyx")
    unrestricted = final_eval(other, val, by_kind, args.eval_frames, None, device)
    grids = {"cells": None if kept is None else int(kept.sum()),
             "unrestricted_cells": int(trainer.field.occupancy.sum()), "unrestricted_psnr": unrestricted["psnr"],
             "unrestricted_ssim": unrestricted["ssim"]}
    trainer.field.set_occupancy(kept)
    threads = torch.get_num_threads()
    result = {
        "command": "python bench/nyx_train.py " + " ".join(sys.argv[1:]),
        "machine": (f"{cpu_description()}, {threads} thread{'' if threads == 1 else 's'}, torch {torch.__version__}"
                    + (f", {torch.cuda.get_device_name(device)}" if device.type == "cuda" else "")),
        "device": device.type,
        "budget_minutes": None if by_iterations else args.minutes,
        "budget_iterations": args.iterations,
        "train_frames": train.n_frames,
        "val_frames": val.n_frames,
        "holdout": holdout_record,
        "val_frames_by_kind": {kind: len(frames) for kind, frames in by_kind.items()},
        "validation_frames_per_kind": NYX_VALIDATION_FRAMES_PER_KIND,
        "holdout_settings": holdout_record["settings"],  # the names of the reports before --holdout
        "holdout_views": holdout_record["views"],
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "load_average_before_after": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
        "carve_seconds": round(trainer.setup_seconds, 1),  # the recipe's look at the data, carving included
        "load_seconds": round(load_s, 1),
        "rss_after_load_mb": round(rss_after_load, 0),
        "iterations": trainer.state.iteration,
        "iterations_per_second": trainer.state.iteration / max(trainer.state.train_seconds, 1e-9),
        "train_seconds": trainer.state.train_seconds,
        "peak_rss_mb": peak_rss_mb(),
        "checkpoint_mb": ckpt.stat().st_size / 1e6,
        "run_states": {"every_s": cfg.checkpoint_every_s, "written": trainer.state.states_written,
                       "seconds": round(trainer.state.state_seconds, 2), "file_mb": round(state_mb, 1)},
        "final_resolution": trainer.field.resolution,
        "recipe": {**cfg.to_dict(),
                   "step_ratio": trainer.render_cfg.step_ratio, "full_step_ratio": trainer.render_cfg.full_step_ratio,
                   "factor_storage": trainer.field.cfg.factor_storage, "upsample_at": list(cfg.upsample_at),
                   "micro_batch_rays": cfg.micro_batch_rays, "micro_batch_samples": cfg.micro_batch_samples},
        "choices": trainer.recipe_choices,
        "full_spacing": trainer.spacing_note,
        "final_grid": grids,
        "box": [[round(float(x), 4) for x in row] for row in trainer.field.aabb.cpu()],
        "final": final,
        "log": trainer.state.log,
    }
    write_report(result, out_dir)
    print(json.dumps({k: v for k, v in result.items() if k != "log"}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
