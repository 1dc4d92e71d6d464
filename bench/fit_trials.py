"""One trial of a change to the method: train a dataset with `visnerf train` for a budget, then
score the checkpoint on the views it trained on, on views held out and on the test path.

Each run appends one row (change, minutes, steps, PSNR on training views, held-out views and the
test path, CPU, commit) to RESULTS/fit_trials.json and rewrites the table RESULTS/fit_trials.md;
``--verdict kept`` / ``--verdict "not kept"`` gives the row its verdict. Extra `visnerf train` flags after
``--`` are the change (none: the recipe as it is).

    python bench/fit_trials.py data/shells_static_800 --minutes 5 --holdout-views 3,10,17 --label "recipe"
    python bench/fit_trials.py data/shells_static_800 --minutes 5 --holdout-views 3,10,17 \
        --label "no total variation" -- --tv-weight-density 0 --tv-weight-appearance 0

Training views are scored on ``--max-frames`` evenly chosen frames of the views trained on (every
frame of a static scene's views), held-out views on all their frames up to the same count, the test
path on every frame where the dataset has one (``--test-frames`` to score fewer).
"""

import visnerf  # noqa: F401  (before torch: it sets the OpenMP wait policy that torch reads once)

# isort: split
import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from bench_common import cpu_description, write_json

from visnerf.evaluation.frames import normalize_params, render_frame
from visnerf.evaluation.ground_truth import load_ground_truth
from visnerf.evaluation.metrics import psnr
from visnerf.inference import load_scene
from visnerf.rendering.render_settings import RenderSettings

ROOT = Path(__file__).resolve().parent.parent
COLUMNS = ("change", "data", "minutes", "steps", "train dB", "held-out dB", "test dB", "test frames", "CPU", "commit",
           "kept")


def evenly(indices: list[int], count: int) -> list[int]:
    """At most ``count`` of ``indices``, evenly spaced, in order."""
    if count >= len(indices):
        return indices
    return [indices[int(i)] for i in np.linspace(0, len(indices) - 1, count).round()]


def mean_psnr(ckpt: Path, data: Path, split: str, frames: list[int] | None, count: int) -> tuple[float | None, int]:
    """Mean PSNR (dB) of the checkpoint's full-quality frames over ``frames`` of ``split`` (None:
    evenly chosen ``count`` of all); (None, 0) where the split is missing."""
    if not (data / f"transforms_{split}.json").exists():
        return None, 0
    scene = load_scene(ckpt, torch.device("cpu"))
    truth = load_ground_truth(data, split, scene.meta.param_axes)
    gt = truth.scene
    chosen = evenly(list(range(gt.n_frames)) if frames is None else frames, count)
    settings = RenderSettings.from_meta(scene.meta, "full")
    scores = []
    for i in chosen:
        params = normalize_params(scene.meta.param_axes, truth.params[i])
        frame = render_frame(scene.field, gt.c2w[i], gt.intrinsics, params, settings)
        scores.append(psnr(frame.rgb, gt.images[i].numpy().astype(np.float32) / 255.0))
    return float(np.mean(scores)), len(chosen)


def view_frames(data: Path, views: set[int]) -> tuple[list[int], list[int]]:
    """Training-split frames (trained on, held out) by the frames' view ids."""
    from visnerf.data.datasets import load_dataset

    ids = load_dataset(data, "train").view_ids.tolist()
    return [i for i, v in enumerate(ids) if v not in views], [i for i, v in enumerate(ids) if v in views]


def steps_of(log: Path) -> int:
    lines = [line for line in log.read_text().splitlines() if line.strip()]
    header = lines[0].split(",")
    return int(float(lines[-1].split(",")[header.index("iteration")]))


def write_table(path: Path, rows: list[dict]) -> None:
    def cell(value: object) -> str:
        text = "-" if value is None else f"{value:.2f}" if isinstance(value, float) else str(value)
        return text.replace("|", "\\|")

    lines = ["# Trials: error against run time", "", "Rows appended by `bench/fit_trials.py` (the command of each "
             "in fit_trials.json). PSNR on the views trained on, on held-out views and on the test path.", "",
             "| " + " | ".join(COLUMNS) + " |", "|" + " --- |" * len(COLUMNS)]
    lines += ["| " + " | ".join(cell(row.get(c)) for c in COLUMNS) + " |" for row in rows]
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    own = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("--minutes", type=float, default=5.0)
    parser.add_argument("--holdout-views", default="3,10,17")
    parser.add_argument("--label", required=True, help="the change, as the table's first column says it")
    parser.add_argument("--max-frames", type=int, default=30)
    parser.add_argument("--test-frames", type=int, default=181)
    parser.add_argument("--work-dir", type=Path, default=ROOT / "runs" / "trials")
    parser.add_argument("--results", type=Path, default=ROOT / "bench" / "results")
    parser.add_argument("--score-data", type=Path, default=None,
                        help="score on this dataset (the same cameras at another size) instead of DATA")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="score this checkpoint (trained as the row says) instead of training one")
    parser.add_argument("--verdict", choices=("kept", "not kept"), default=None)
    args = parser.parse_args(own)
    args.work_dir.mkdir(parents=True, exist_ok=True)
    slug = "".join(c if c.isalnum() else "_" for c in f"{args.data.name}_{args.label}")[:80]
    ckpt = args.work_dir / f"{slug}.safetensors"
    command = [sys.executable, "-m", "visnerf", "train", str(args.data), "--out", str(ckpt), "--time-budget",
               f"{args.minutes:g}", "--holdout-views", args.holdout_views, *extra]
    started = time.perf_counter()
    if args.checkpoint is None:
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        trained_s = time.perf_counter() - started
    else:
        ckpt, trained_s = args.checkpoint, 60.0 * args.minutes
    held = {int(v) for v in args.holdout_views.split(",") if v}
    scored = args.score_data or args.data
    trained, held_out = view_frames(scored, held)
    train_db, _ = mean_psnr(ckpt, scored, "train", trained, args.max_frames)
    held_db, _ = mean_psnr(ckpt, scored, "train", held_out, args.max_frames) if held_out else (None, 0)
    test_db, n_test = mean_psnr(ckpt, scored, "test", None, args.test_frames)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "model"], capture_output=True,
                           text=True, cwd=ROOT).stdout.strip()
    commit += "+changes" if dirty else ""
    row = {"change": args.label, "data": args.data.name + ("" if args.score_data is None else f", scored on {scored.name}"), "minutes": args.minutes, "wall_s": round(trained_s),
           "steps": steps_of(ckpt.with_suffix(".log.csv")), "train dB": train_db, "held-out dB": held_db,
           "test dB": test_db, "test frames": n_test, "CPU": cpu_description(), "commit": commit,
           "kept": args.verdict, "command": "python bench/fit_trials.py " + " ".join(argv),
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    record_path = args.results / "fit_trials.json"
    rows = json.loads(record_path.read_text())["trials"] if record_path.exists() else []
    rows.append(row)
    write_json(record_path, {"trials": rows})
    write_table(args.results / "fit_trials.md", rows)
    print(json.dumps(row, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
