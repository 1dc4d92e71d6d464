"""The bundled checkpoints' record: RESULTS/bundled_eval/bundled.json, its index and the README's table.

Each bundled scene keeps the figures of the run that trained it, with that run's budget, command,
CPU, date and report, so that a run of some of them (``scripts/train_bundled.sh tangle_iso``)
replaces their rows and keeps the others' (``bench/eval_scenes.py --bundle``).
"""

import json
import os
from pathlib import Path

from bench_common import replace_marked_section, table_cell

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


def table_lines(record: dict, link_root: Path, root: Path) -> list[str]:
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
             *table_lines(record, link_root, root), ""]
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
                                      "\n".join(table_lines(record, readme.parent, root)))
        if text is None:
            raise ValueError(f"{readme} has no {BEGIN} ... {END} section")
        readme.write_text(text)
    return record
