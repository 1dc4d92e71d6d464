"""Train and evaluate every synthetic scene under a fixed wall-clock budget; tabulate error and time.

For each scene of ``visnerf scenes``: generate the dataset at ``--res`` (the full protocol: the
scene's icosphere views per parameter setting, a 181-view test path between training values), train under
``--minutes-per-scene`` with views 3, 11 and 25 held out for validation, evaluate the checkpoint on
the test path as ``visnerf eval`` does (per-scene report in RESULTS/eval_scenes/NAME/, or
RESULTS/eval_scenes.partial/NAME/ for a partial run, RESULTS/bundled_eval/NAME/ for a partial run
with ``--bundle``, whose rows replace theirs in RESULTS/bundled_eval/bundled.json), and write one
table (scene, K, PSNR, SSIM, training minutes, ms per frame, model MB) next to the paper's figures
where the paper has a corresponding row.

    python bench/eval_scenes.py --minutes-per-scene 4              # all scenes, 4 min each, 128x128
    python bench/eval_scenes.py --scenes tangle_static --minutes-per-scene 0.5 --res 32 --test-views 8

The Nyx witness: cosmo_sim (3 simulation parameters, 3 values each, DVR) has ground truth on its
181-frame test path, where every parameter lies between training values and the paper's Nyx test
path is not to be had; one line trains it with the product's recipe for N minutes and prints its
test-path PSNR / SSIM, overall and by place in parameter space (at / between training values, one
parameter moving / all moving), also in the .md and .json:

    python bench/eval_scenes.py --scenes cosmo_sim --minutes-per-scene 10 --data-root data/eval --results /tmp/cosmo_witness

A full run (every scene at 128x128) writes bench/results/eval_scenes.{json,md}; any other run writes
eval_scenes.partial.{json,md}.
"""

import visnerf  # noqa: F401  (before torch: it sets the OpenMP wait policy that torch reads once)

# isort: split
import argparse
import dataclasses
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import torch
from bench_common import cpu_description, replace_marked_section, table_cell, write_json

from visnerf import runtime
from visnerf.config import FieldConfig, HoldoutConfig, TrainConfig
from visnerf.data.datasets import load_dataset
from visnerf.data.holdout import split_holdout
from visnerf.evaluation.evaluate import EvalConfig, evaluate_checkpoint
from visnerf.evaluation.plots import plot_training_curves
from visnerf.evaluation.report import write_report
from visnerf.evaluation.sweeps import SweepConfig
from visnerf.evaluation.training_curves import read_training_log
from visnerf.runtime import pick_device
from visnerf.scenes.catalog import SceneSpec, scene_catalog
from visnerf.scenes.writer import DatasetOptions, write_scene
from visnerf.training.recipe import recipe_trainer
from visnerf.training.trainer import Trainer

# The bundled checkpoints' record: RESULTS/bundled_eval/bundled.json, its index and the README's
# table. Each bundled scene keeps the figures of the run that trained it (budget, command, CPU, date,
# report), so that a run of some of them (``scripts/train_bundled.sh tangle_iso``) replaces their
# rows and keeps the others' (``--bundle``).

BUNDLED = ("plume_time", "tangle_iso", "vortex_tf1", "cosmo_sim")
"""The scenes shipped in checkpoints/: one of each slider kind the product exists for."""
SLIDERS = {"plume_time": "timestep", "tangle_iso": "isovalue", "vortex_tf1": "transfer function",
           "cosmo_sim": "3 simulation parameters"}
BEGIN, END = "<!-- bundled:begin -->", "<!-- bundled:end -->"
"""Markers of the README's bundled-checkpoint table."""
FIGURES = ("kind", "psnr", "ssim", "model_mb", "iterations", "train_minutes", "holdout_views")
"""The row fields of ``bench/eval_scenes.py`` a bundled scene keeps (``holdout_views``: the views
left out of its training, none for a scene trained on every view as `visnerf train DATA` does)."""


def bundle_entry(row: dict, record: dict, report: Path, root: Path, rescored: bool = False) -> dict:
    """The record of one bundled scene: ``row`` of the run ``record`` whose report is ``report``;
    ``rescored``: the run evaluated an earlier run's checkpoint again without training it."""
    missing = [k for k in ("scene", *FIGURES) if k not in row]
    if missing:
        raise ValueError(f"row of {row.get('scene', '?')} lacks {missing}")
    return {
        "scene": row["scene"], **{k: row[k] for k in FIGURES}, "minutes": record["minutes_per_scene"],
        "command": record["command"], "cpu": record["machine"].get("cpu", ""),
        "threads": record["machine"]["torch_threads"], "date": record["date"], "rescored": rescored,
        "report": report.relative_to(root).as_posix() if report.is_relative_to(root) else str(report),
    }  # fmt: skip


def merge_entries(path: Path, entries: list[dict]) -> dict:
    """``path``'s record with ``entries`` replacing the rows of their scenes, in ``BUNDLED`` order;
    written whole through a temporary file."""
    unknown = [e["scene"] for e in entries if e["scene"] not in BUNDLED]
    if unknown:
        raise ValueError(f"{unknown} are not bundled scenes ({', '.join(BUNDLED)})")
    scenes = {e["scene"]: e for e in json.loads(path.read_text())["scenes"]} if path.exists() else {}
    scenes.update({e["scene"]: e for e in entries})
    record = {"scenes": [scenes[name] for name in BUNDLED if name in scenes]}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(record, indent=1) + "\n")
    tmp.replace(path)
    return record


def bundled_table_lines(record: dict, link_root: Path, root: Path) -> list[str]:
    """The bundled scenes' table, each report linked relative to ``link_root``."""
    lines = ["| scene | slider | trained (min) | test-path PSNR (dB) | SSIM | model MB | report |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for e in record["scenes"]:
        report = os.path.relpath(root / e["report"], link_root)
        lines.append(f"| `{e['scene']}` | {SLIDERS.get(e['scene'], e['kind'])} ({e['kind']}) | {e['minutes']:g} | "
                     f"{table_cell(e['psnr'], 2)} | {table_cell(e['ssim'], 3)} | {table_cell(e['model_mb'], 2)} | [report]({report}) |")
    return lines


def index_lines(record: dict, link_root: Path, root: Path) -> list[str]:
    """RESULTS/bundled_eval/README.md: the table, then the run behind each row."""
    lines = ["# The bundled checkpoints on their test paths", "",
             "Each trained with the product's recipe (no flags) for the minutes given, on both threads, and scored "
             "on its 181-frame test path; `scripts/train_bundled.sh` reruns them.", "",
             *bundled_table_lines(record, link_root, root), ""]
    for e in record["scenes"]:
        how = "evaluated again (not retrained: the steps are its training run's)" if e.get("rescored") else "trained"
        held = e["holdout_views"]
        views = f", views {', '.join(map(str, held))} held out" if held else " on every view"
        lines.append(f"- `{e['scene']}`: {how} by `{e['command']}` ({e['cpu']}, {e['threads']} threads, "
                     f"{e['date'][:10]}); {e['iterations']} steps in {e['train_minutes']:.1f} min{views}.")
    return lines


def write_bundle_record(results: Path, root: Path, entries: list[dict], readme: Path | None) -> dict:
    """Merge ``entries`` into RESULTS/bundled_eval/bundled.json, rewrite the index beside it and,
    given ``readme``, the table between its markers."""
    folder = results / "bundled_eval"
    record = merge_entries(folder / "bundled.json", entries)
    (folder / "README.md").write_text("\n".join(index_lines(record, folder, root)) + "\n")
    if readme is not None:
        text = replace_marked_section(readme.read_text(), BEGIN, END,
                                      "\n".join(bundled_table_lines(record, readme.parent, root)))
        if text is None:
            raise ValueError(f"{readme} has no {BEGIN} ... {END} section")
        readme.write_text(text)
    return record


ROOT = Path(__file__).resolve().parents[1]
HOLDOUT_VIEWS = (3, 11, 25)

# The paper's figures for the real datasets these scenes stand in for (181 test views each).
PAPER_PSNR = {
    "plume_time": ("five jets, timestep", 27.51),
    "tangle_iso": ("Tangaroa, isosurfaces", 29.36),
    "vortex_tf1": ("vortex, TF-1", 37.26),
    "vortex_tf2": ("vortex, TF-2", 36.58),
    "cosmo_sim": ("Nyx-DVR, 3 simulation parameters", 30.02),
}
PAPER_STATIC = ("static scenes", "27.0 to 38.7")


def machine(device: torch.device) -> dict:
    return {
        "platform": f"{platform.machine()} {platform.system()}",
        "cpu_cores": os.cpu_count(),
        "device": str(device),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "cpu": cpu_description(),
    }


def dataset_for(spec: SceneSpec, root: Path, options: DatasetOptions, workers: int) -> tuple[Path, float]:
    """The scene's dataset (reused when one with the same size is there) and the seconds spent making it."""
    folder = root / f"{spec.name}_{options.resolution}"
    try:
        test = json.loads((folder / "transforms_test.json").read_text())
        train = json.loads((folder / "transforms_train.json").read_text())
        if (test["generator"]["resolution"][0] == options.resolution and len(test["frames"]) == options.n_test_views
                and train["generator"]["views_per_setting"] == options.n_views):
            return folder, 0.0
    except (OSError, KeyError, IndexError, json.JSONDecodeError):
        pass
    summary = write_scene(spec, folder, options, progress=False, workers=workers)
    return folder, summary.seconds


def train_scene(data: Path, ckpt: Path, minutes: float, device: torch.device,
                holdout_views: tuple[int, ...] = HOLDOUT_VIEWS) -> Trainer:
    """Train under the budget with the product's recipe, as `visnerf train DATA --time-budget MINUTES
    --holdout-views ...` does (the recipe's look at the data counts as training time, validation
    does not); with no ``holdout_views``, on every view, as `visnerf train DATA` does."""
    train, val = split_holdout(load_dataset(data, "train"), HoldoutConfig(views=holdout_views))
    budget = 60.0 * minutes
    base = TrainConfig(time_budget_s=budget, validate_every_s=max(budget / 6.0, 5.0))
    trainer = recipe_trainer(train, val, base, FieldConfig(), device)
    trainer.run(progress_bar=False)
    trainer.save(ckpt, dataset=str(data))
    return trainer


def evaluation_fields(summary: dict) -> dict:
    """A row's figures from the evaluation of its checkpoint (``write_report``'s summary)."""
    m, groups = summary["metrics"], summary["parameter_space"]["groups"]
    return {
        "frames": m["n"], "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"], "ms_per_frame": m["ms_median"],
        "model_mb": summary["model_mb"], "psnr_between_training_values": groups["between_training_values"]["psnr"],
        "parameter_space": {name: {"n": g["n"], "psnr": g["psnr"], "ssim": g["ssim"]} for name, g in groups.items()},
    }  # fmt: skip


def scene_row(spec: SceneSpec, summary: dict, trainer: Trainer, gen_seconds: float,
              holdout_views: tuple[int, ...]) -> dict:
    paper = PAPER_PSNR.get(spec.name) if spec.axes else PAPER_STATIC
    return {
        "scene": spec.name, "kind": spec.kind, "K": len(spec.axes), "holdout_views": list(holdout_views),
        **evaluation_fields(summary),
        "train_minutes": trainer.state.train_seconds / 60.0, "iterations": trainer.state.iteration,
        "resolution": list(trainer.field.resolution), "generation_seconds": gen_seconds, "views": spec.n_views,
        "choices": trainer.recipe_choices, "paper": None if paper is None else {"dataset": paper[0], "psnr": paper[1]},
    }  # fmt: skip


def bundle_scene(ckpt: Path, folder: Path) -> None:
    """Copy a trained scene and its training log into the bundled checkpoints, each file replaced whole."""
    folder.mkdir(parents=True, exist_ok=True)
    for src in (ckpt, ckpt.with_suffix(".log.csv"), ckpt.with_suffix(".log.json")):
        tmp = folder / (src.name + ".tmp")
        shutil.copyfile(src, tmp)
        tmp.replace(folder / src.name)


def table_lines(record: dict) -> list[str]:
    """The results table, with the paper's PSNR on the real dataset each scene stands in for, and
    a note on the rows rerun since the record, one group of day, CPU and command a line."""
    lines = [
        "| scene | kind | K | PSNR (dB) | SSIM | iterations | grid | ms per frame | model MB | paper: real counterpart, PSNR |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    reruns = [r for r in record["scenes"] if r.get("rerun")]
    for r in record["scenes"]:
        paper = r["paper"]
        grid = "x".join(map(str, r["resolution"])) if r.get("resolution") else "n/a"
        name = r["scene"] + (" *" if r.get("rerun") else "")
        lines.append(f"| {name} | {r['kind']} | {r['K']} | {table_cell(r['psnr'], 2)} | {table_cell(r['ssim'], 3)} | "
                     f"{r.get('iterations', 'n/a')} | {grid} | {table_cell(r['ms_per_frame'], 0)} | {table_cell(r['model_mb'], 2)} | "
                     f"{'-' if not paper else paper['dataset'] + ', ' + str(paper['psnr'])} |")
    # One note naming every rerun, grouped by day, CPU and command; the CPU only where it is not
    # the record's.
    groups: dict[tuple[str, str, str, bool], list[str]] = {}
    for r in reruns:
        rerun = r["rerun"]
        key = (rerun["date"][:10], rerun["cpu"], rerun["command"], rerun.get("rescored", False))
        groups.setdefault(key, []).append(r["scene"])
    each = [", ".join(scenes) + f" ({date}"
            + ("" if cpu == record["machine"].get("cpu", "") else f", {cpu}")
            + (f", `{command}`" if command else "")
            + (", evaluated again, not retrained" if rescored else "") + ")"
            for (date, cpu, command, rescored), scenes in sorted(groups.items())]
    if not each:
        return lines
    return [*lines, "", "\\* Rerun after a change that concerns them (the other rows are the record's):", "",
            *(f"- {text}" for text in each)]


PLACES = {"at_training_values": "at training values", "between_training_values": "between training values",
          "one_moving": "one parameter moving", "all_moving": "all parameters moving"}
"""The groups of ``visnerf eval``'s split by place in parameter space that the tables show."""


def place_cell(group: dict | None) -> str:
    """"PSNR / SSIM (n)" of one group of test frames; "no frame" for an empty one, "-" where not recorded."""
    if group is None:
        return "-"
    if not group["n"]:
        return "no frame"
    return f"{table_cell(group['psnr'], 2)} / {table_cell(group['ssim'], 3)} ({group['n']})"


def place_lines(record: dict) -> list[str]:
    """Each scene's test-path PSNR / SSIM by place in parameter space (rows recorded before the
    split was kept have none; a static scene has no parameter to move)."""
    rows = [r for r in record["scenes"] if r.get("parameter_space") and r["K"] > 0]
    if not rows:
        return []
    lines = ["Test-path PSNR (dB) / SSIM (frames) by place in parameter space (the protocol's test path keeps "
             "every parameter between training values; `visnerf eval`'s report of each scene gives more):", "",
             "| scene | " + " | ".join(PLACES.values()) + " |", "|" + " --- |" * (1 + len(PLACES))]
    for r in rows:
        lines.append(f"| {r['scene']} | " + " | ".join(place_cell(r["parameter_space"].get(g)) for g in PLACES) + " |")
    return [*lines, ""]


def views_per_setting(record: dict) -> str:
    """Views per parameter setting: the protocol's, or each scene's own where they differ."""
    counts = {r["scene"]: r.get("views", record["views"]) for r in record["scenes"]}
    if len(set(counts.values())) <= 1:
        return f"{next(iter(counts.values()), record['views'])} views per parameter setting"
    return "views per parameter setting: " + ", ".join(f"{scene} {n}" for scene, n in counts.items())


def write_markdown(path: Path, record: dict) -> None:
    m = record["machine"]
    lines = [
        "# Synthetic scenes: error against training and rendering time",
        "",
        f"`{record['command']}` on {m.get('cpu', m['platform'])}, {m['cpu_cores']} CPU cores, device {m['device']}, "
        f"torch {m['torch']} with {m['torch_threads']} thread(s), {record['date']}.",
        "",
        f"Each scene: dataset at {record['resolution']}x{record['resolution']} ({views_per_setting(record)}), training for {record['minutes_per_scene']:g} minute(s) of wall-clock time "
        "(the product's recipe, no flags) with views "
        f"{', '.join(map(str, HOLDOUT_VIEWS))} held out, then `visnerf eval` on {record['test_views']} test views "
        "(parameters between training values). PSNR and SSIM are means over the evaluated test frames, "
        "ms per frame the median full-quality render time.",
        "",
        *table_lines(record),
        "",
        *place_lines(record),
        "Per-scene reports (per-frame error, CIELUV difference images, render-settings sweep, training "
        f"curve): `{record['reports']}/NAME/report.md`. Training curves of all scenes: "
        f"`{record['training_figure']}`.",
        "",
    ]
    path.write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    catalog = scene_catalog()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=list(catalog), choices=list(catalog), metavar="NAME")
    parser.add_argument("--minutes-per-scene", type=float, default=10.0, help="training budget (default 10)")
    parser.add_argument("--res", type=int, default=128, help="image size (default 128)")
    parser.add_argument("--bundle", type=Path, default=None, metavar="DIR",
                        help=f"train {', '.join(BUNDLED)} on every view, as `visnerf train DATA` does (the others "
                             "keep the hold-out), copy their checkpoints (and logs) into DIR and replace their rows "
                             "in RESULTS/bundled_eval/ and the README's bundled table; their reports go to "
                             "RESULTS/bundled_eval/NAME/ (scripts/train_bundled.sh)")
    parser.add_argument("--test-views", type=int, default=181, help="views on the test path (default 181)")
    parser.add_argument("--max-eval-frames", type=int, default=None, help="evaluate only N test frames")
    parser.add_argument("--sweep-frames", type=int, default=4, help="frames per render setting (default 4)")
    parser.add_argument("--data-root", type=Path, help="datasets (reused when present; default: temporary)")
    parser.add_argument("--work-dir", type=Path, help="checkpoints and logs (default: temporary)")
    parser.add_argument("--results", type=Path, default=ROOT / "bench" / "results", help="results folder")
    parser.add_argument("--workers", type=int, default=2, help="scene generation processes (default 2)")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    parser.add_argument("--replace-rows", action="store_true",
                        help="rerun the named scenes the record's way and replace their rows and reports in "
                             "RESULTS/eval_scenes.json and .md and the README, each marked with its date and command")
    parser.add_argument("--rescore", action="store_true",
                        help="with --replace-rows and --work-dir: evaluate the record's checkpoints of the named "
                             "scenes in the work folder again with the current renderer, without training (their "
                             "training figures stay the record's); for a change that concerns rendering only")
    args = parser.parse_args(argv)
    if args.rescore and not (args.replace_rows and args.work_dir):
        parser.error("--rescore needs --replace-rows and --work-dir (the folder of the record's checkpoints)")
    if args.bundle is not None and args.replace_rows and not args.rescore and set(args.scenes) & set(BUNDLED):
        parser.error(f"--bundle trains {', '.join(sorted(set(args.scenes) & set(BUNDLED)))} on every view and the "
                     f"record's rows hold views {', '.join(map(str, HOLDOUT_VIEWS))} out: run --bundle and "
                     "--replace-rows apart")
    if args.minutes_per_scene <= 0 or args.res < 8 or args.test_views < 2:
        parser.error("--minutes-per-scene must be positive, --res at least 8, --test-views at least 2")
    runtime.configure(args.threads)
    device = pick_device(args.device)
    full_run = args.res == 128 and args.scenes == list(catalog) and args.test_views == 181 and not args.max_eval_frames
    if args.replace_rows:
        record_path = args.results / "eval_scenes.json"
        if not record_path.exists():
            parser.error(f"--replace-rows needs the record {record_path}")
        kept = json.loads(record_path.read_text())
        if (args.res, args.test_views, args.minutes_per_scene) != (kept["resolution"], kept["test_views"],
                                                                   kept["minutes_per_scene"]) or args.max_eval_frames:
            parser.error("--replace-rows reruns scenes the record's way: its --res, --test-views and "
                         "--minutes-per-scene, every test frame")
    stem = "eval_scenes" if full_run or args.replace_rows else "eval_scenes.partial"  # a partial run never replaces the record
    if args.bundle is not None and full_run:
        parser.error("--bundle trains the bundled scenes on every view, not the record's way: name the scenes")
    temporary = Path(tempfile.mkdtemp(prefix="visnerf_eval_scenes_"))
    data_root, work = args.data_root or temporary / "data", args.work_dir or temporary / "runs"
    # a bundled scene's report must outlive the next partial run
    reports = args.results / ("bundled_eval" if args.bundle is not None and stem.endswith("partial") else stem)
    options = DatasetOptions(resolution=args.res, n_test_views=args.test_views)
    eval_cfg = EvalConfig(split="test", max_frames=args.max_eval_frames, sweep=SweepConfig(n_frames=args.sweep_frames))
    record = {
        "command": "python bench/eval_scenes.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()), "machine": machine(device),
        "resolution": args.res, "views": options.n_views, "test_views": args.test_views,
        "minutes_per_scene": args.minutes_per_scene, "reports": str(reports.relative_to(ROOT))
        if reports.is_relative_to(ROOT) else str(reports), "scenes": [],
    }  # fmt: skip
    runs = []
    try:
        for name in args.scenes:
            spec = catalog[name]
            data, gen_seconds = dataset_for(spec, data_root, dataclasses.replace(options, n_views=spec.n_views),
                                            args.workers)
            ckpt = work / f"{name}.safetensors"
            if args.rescore:
                row = next((r for r in kept["scenes"] if r["scene"] == name), None)
                if row is None or not ckpt.exists():
                    parser.error(f"--rescore: {name} has no row in the record or no checkpoint {ckpt}")
                print(f"{name}: evaluating {ckpt} again", file=sys.stderr)
            else:
                holdout = () if args.bundle is not None and name in BUNDLED else HOLDOUT_VIEWS
                print(f"{name}: training {args.minutes_per_scene:g} min on {data}, "
                      + (f"views {', '.join(map(str, holdout))} held out" if holdout else "every view"), file=sys.stderr)
                trainer = train_scene(data, ckpt, args.minutes_per_scene, device, holdout)
            summary = write_report(evaluate_checkpoint(ckpt, data, eval_cfg, device), eval_cfg, reports / name)
            if args.rescore:
                # every row of the record was trained with the hold-out (a bundling run does not replace rows)
                record["scenes"].append({"holdout_views": list(HOLDOUT_VIEWS), **row, **evaluation_fields(summary)})
            else:
                record["scenes"].append(scene_row(spec, summary, trainer, gen_seconds, holdout))
                del trainer
            if args.bundle is not None and name in BUNDLED:
                bundle_scene(ckpt, args.bundle)
            runs.append(read_training_log(ckpt.with_suffix(".log.csv"), name=name))
            places = record["scenes"][-1]["parameter_space"]
            print(f"{name}: PSNR {table_cell(summary['metrics']['psnr'], 2)} dB, SSIM {table_cell(summary['metrics']['ssim'], 3)} on "
                  f"{summary['metrics']['n']} test frames; PSNR / SSIM (frames) "
                  + "; ".join(f"{PLACES[g]} {place_cell(places[g])}" for g in PLACES if g in places), file=sys.stderr)
    finally:
        shutil.rmtree(temporary, ignore_errors=True)
    if args.bundle is not None:
        write_bundle_record(args.results, ROOT, [bundle_entry(r, record, reports / r["scene"] / "report.md", ROOT, args.rescore)
                                                 for r in record["scenes"] if r["scene"] in BUNDLED],
                            ROOT / "README.md" if args.results == ROOT / "bench" / "results" else None)
    if args.replace_rows:
        replaced = {r["scene"]: {**r, "rerun": {"date": record["date"], "command": record["command"],
                                                "cpu": record["machine"].get("cpu", ""), "rescored": args.rescore}}
                    for r in record["scenes"]}
        record = {**kept, "scenes": [replaced.get(r["scene"], r) for r in kept["scenes"]]}
        write_json(args.results / f"{stem}.json", record)
        write_markdown(args.results / f"{stem}.md", record)
        print(f"rows of {', '.join(replaced)} replaced in {args.results / stem}.json and .md", file=sys.stderr)
        return 0
    figure = args.results / f"{stem}_training.png"
    plot_training_curves(figure, runs)
    record["training_figure"] = str(figure.relative_to(ROOT)) if figure.is_relative_to(ROOT) else str(figure)
    args.results.mkdir(parents=True, exist_ok=True)
    write_json(args.results / f"{stem}.json", record)
    write_markdown(args.results / f"{stem}.md", record)
    print(f"results -> {args.results / stem}.json and .md", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
