"""Train on shared/data/nyx under a wall-clock budget and record what it reaches.

Held out for validation: four whole parameter settings (interpolation between training settings)
and four views at every other setting. Records validation PSNR/SSIM against training time,
iterations per second, peak RSS, checkpoint size and seconds per 256x256 frame.

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
figures in columns and the validation PSNR at each validation with its difference from the first
run (``--about`` adds a paragraph on what they share and differ in); it trains nothing.

    .venv/bin/python bench/nyx_train.py --side-by-side bench/results/nyx_product_vs_tuned_2 \\
        --run tuned="the tuned recipe" --run product="the product" --title "Nyx, side by side"
"""

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from bench_common import (
    HOLDOUT_SETTINGS,
    HOLDOUT_VIEWS,
    ROOT,
    cpu_description,
    evenly_spaced,
    holdout_for,
    render_frame,
    write_json,
)

from visnerf.commands import positive_float, positive_int
from visnerf.config import FieldConfig, TrainConfig
from visnerf.data.holdout import split_holdout
from visnerf.data.parsers.blender import load_dataset
from visnerf.evaluation.colour_difference import luv_difference
from visnerf.evaluation.evaluate import EvalConfig
from visnerf.evaluation.metrics import psnr, ssim
from visnerf.evaluation.plots import plot_difference
from visnerf.inference import load_scene
from visnerf.runtime import pick_device
from visnerf.training.recipe import recipe_trainer
from visnerf.training.run_state import run_state_path

NYX_VALIDATION_FRAMES = 6
"""Held-out frames of each periodic validation (the final evaluation renders ``--eval-frames``)."""


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def final_eval(ckpt: Path, val, n_frames: int, figure: Path | None = None,
               device: torch.device | None = None) -> dict:
    """Render ``n_frames`` evenly chosen held-out frames through the public inference API; with
    ``figure``, save the frame of median PSNR beside its ground truth and their CIELUV difference."""
    scene = load_scene(ckpt, device or torch.device("cpu"))
    rows = []
    for i in evenly_spaced(val.n_frames, n_frames):
        t0 = time.perf_counter()
        pred, gt = render_frame(scene, val, i, 256, 256)
        seconds = time.perf_counter() - t0
        held_setting = any(np.allclose(val.params[i].numpy(), s, atol=1e-6) for s in HOLDOUT_SETTINGS)
        rows.append({"frame": int(i), "psnr": psnr(pred, gt), "ssim": ssim(pred, gt), "seconds": seconds,
                     "held_out": "setting" if held_setting else "view", "images": (pred, gt)})
    if figure is not None:
        median = sorted(rows, key=lambda r: r["psnr"])[len(rows) // 2]
        pred, gt = median["images"]
        plot_difference(figure, pred, gt, luv_difference(pred, gt), EvalConfig.difference_scale_max,
                        f"held-out frame {median['frame']} (at a held-out {median['held_out']}), "
                        f"the median of {len(rows)}: {median['psnr']:.2f} dB")
    for r in rows:
        del r["images"]
    return {
        "frames": len(rows),
        "psnr": float(np.mean([r["psnr"] for r in rows])),
        "ssim": float(np.mean([r["ssim"] for r in rows])),
        "psnr_held_out_settings": float(np.mean([r["psnr"] for r in rows if r["held_out"] == "setting"] or [np.nan])),
        "psnr_held_out_views": float(np.mean([r["psnr"] for r in rows if r["held_out"] == "view"] or [np.nan])),
        "seconds_per_frame_256_median": float(np.median([r["seconds"] for r in rows])),
    }


def write_report(result: dict, out_dir: Path) -> None:
    write_json(out_dir / "nyx_train.json", result)
    f = result["final"]
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
        f"| iterations | {result['iterations']} ({result['iterations_per_second']:.2f} it/s) |",
        f"| held-out PSNR / SSIM ({f['frames']} frames) | {f['psnr']:.2f} dB / {f['ssim']:.3f} |",
        f"| PSNR at held-out parameter settings | {f['psnr_held_out_settings']:.2f} dB |",
        f"| PSNR at held-out views | {f['psnr_held_out_views']:.2f} dB |",
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
        "Validation PSNR against training time:",
        "",
        "| train s | iteration | train PSNR | val PSNR | val SSIM | grid | occupied cells |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in result["log"]:
        lines.append(f"| {row['train_seconds']:.0f} | {row['iteration']} | {row['train_psnr']:.2f} | "
                     f"{row.get('val_psnr', float('nan')):.2f} | {row.get('val_ssim', float('nan')):.3f} | "
                     f"{row.get('resolution', '')} | {row.get('occupied_cells', '')} |")
    lines += ["", "![validation PSNR against training time](nyx_train.png)", "",
              "![the held-out frame of median PSNR](nyx_heldout.png)", ""]
    (out_dir / "nyx_train.md").write_text("\n".join(lines))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 3.5))
        log = result["log"]
        ax.plot([r["train_seconds"] / 60 for r in log], [r.get("val_psnr", np.nan) for r in log], "o-", label="held-out")
        ax.plot([r["train_seconds"] / 60 for r in log], [r["train_psnr"] for r in log], "--", label="train (EMA)")
        ax.axhline(28.0, color="gray", lw=0.8, ls=":", label="target 28 dB")
        ax.set_xlabel("training minutes (2-core CPU)")
        ax.set_ylabel("PSNR (dB)")
        ax.legend()
        ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(out_dir / "nyx_train.png", dpi=110)
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
    def row(name: str, cell) -> str:  # noqa: ANN001
        return f"| {name} | " + " | ".join(cell(r) for r in runs) + " |"

    return [
        "| | " + " | ".join(labels) + " |",
        "| --- | " + " | ".join("---" for _ in runs) + " |",
        row(f"held-out PSNR / SSIM ({runs[0]['final']['frames']} frames)",
            lambda r: f"{r['final']['psnr']:.2f} dB / {r['final']['ssim']:.3f}"),
        row("at held-out settings / views",
            lambda r: f"{r['final']['psnr_held_out_settings']:.2f} / {r['final']['psnr_held_out_views']:.2f} dB"),
        row("iterations", lambda r: f"{r['iterations']} ({r['iterations_per_second']:.2f} it/s)"),
        row("peak RSS", lambda r: f"{r['peak_rss_mb']:.0f} MB"),
        row("checkpoint", lambda r: f"{r.get('checkpoint_mb', float('nan')):.2f} MB"),
        row("full-quality spacing chosen", lambda r: spacing_chosen(r.get("full_spacing"))),
        row("seconds per 256x256 frame (median)", lambda r: f"{r['final']['seconds_per_frame_256_median']:.2f}"),
    ]


def validation_table(labels: list[str], runs: list[dict[str, Any]]) -> list[str]:
    """One line per validation, matched by order: the runs validate every ``--validate-every``
    seconds of training, but a step or a milestone can carry one past that; the first column gives
    each run's own training seconds."""
    rows = [validation_rows(r) for r in runs]
    head = "| train s | " + " | ".join(f"iterations ({lab}) | val PSNR ({lab})" for lab in labels)
    head += "".join(f" | {labels[0]} minus {lab}" for lab in labels[1:]) + " |"
    lines = [head, "|" + " --- |" * (3 * len(runs))]  # train s; 2 per run; a difference per other run
    for i in range(min(len(r) for r in rows)):
        at = [r[i] for r in rows]
        cells = [" / ".join(f"{a['train_seconds']:.0f}" for a in at)]
        for a in at:
            cells += [str(a["iteration"]), f"{a['val_psnr']:.2f}"]
        cells += [f"{at[0]['val_psnr'] - a['val_psnr']:+.2f} dB" for a in at[1:]]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


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
    lines += ["", *summary_table(labels, results), "",
              f"Validation PSNR (bench/nyx_train.py validates on {NYX_VALIDATION_FRAMES} held-out frames) "
              "against training time:", "",
              *validation_table(labels, results), ""]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "nyx"))
    ap.add_argument("--minutes", type=positive_float, default=60.0)
    ap.add_argument("--iterations", type=positive_int, default=None,
                    help="schedule by this many iterations instead of --minutes (a GPU run, to see "
                         "what more iterations of the same recipe reach)")
    ap.add_argument("--device", default="cpu", help="cpu (default), cuda or auto")
    ap.add_argument("--validate-every", type=positive_float, default=300.0, help="seconds of training")
    ap.add_argument("--eval-frames", type=positive_int, default=24)
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
    train, val = split_holdout(scene, holdout_for(scene))
    del scene
    assert val is not None
    if args.figure_only:
        Path(args.results).mkdir(parents=True, exist_ok=True)
        print(json.dumps(final_eval(Path(args.figure_only), val, args.eval_frames, Path(args.results) / "nyx_heldout.png")))
        return 0
    by_iterations = args.iterations is not None
    # The product's recipe (what `visnerf train` runs); only the budget and the validation are this bench's.
    base = TrainConfig(iterations=args.iterations if by_iterations else 10**9,
                       time_budget_s=None if by_iterations else args.minutes * 60,
                       validate_every_s=args.validate_every, validate_max_images=NYX_VALIDATION_FRAMES)
    trainer = recipe_trainer(train, val, base, FieldConfig(), device)
    cfg = trainer.cfg
    state_path = run_state_path(args.out)  # written every checkpoint_every_s, as `visnerf train` does
    trainer.run(progress_bar=sys.stderr.isatty(), on_validate=lambda row: print(json.dumps(row), flush=True),
                state_path=state_path)
    ckpt = trainer.save(args.out, dataset="shared/data/nyx")
    state_mb = state_path.stat().st_size / 1e6
    state_path.unlink()
    out_dir = Path(args.results)
    out_dir.mkdir(parents=True, exist_ok=True)
    final = final_eval(ckpt, val, args.eval_frames, out_dir / "nyx_heldout.png", device)
    # The same trained field with the inference grid the trainer built before finish_occupancy:
    # the density's occupancy now, not limited to the cells training last sampled.
    kept = trainer.field.occupancy
    trainer.update_occupancy(shrink=False)
    other = trainer.save(Path(args.out).with_name(Path(args.out).stem + "_unrestricted.safetensors"), dataset="shared/data/nyx")
    unrestricted = final_eval(other, val, args.eval_frames, None, device)
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
        "holdout_settings": HOLDOUT_SETTINGS,
        "holdout_views": HOLDOUT_VIEWS,
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
