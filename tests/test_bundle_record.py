"""The bundled record of bench/eval_scenes.py: a run of some bundled scenes replaces their rows and keeps the others'."""

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from eval_scenes import BEGIN, END, bundle_entry, write_bundle_record  # noqa: E402


def _run(tmp: Path, scenes: dict[str, float], minutes: float, command: str,
         holdout_views: tuple[int, ...] = ()) -> tuple[dict, list[dict]]:
    record = {"command": command, "date": "2026-11-27 10:00:00 UTC", "minutes_per_scene": minutes,
              "machine": {"cpu": "AMD EPYC", "torch_threads": 2}}
    rows = [{"scene": name, "kind": "ir" if name == "tangle_iso" else "dvr", "psnr": psnr, "ssim": 0.97,
             "model_mb": 2.2, "iterations": 100, "train_minutes": minutes, "holdout_views": list(holdout_views)}
            for name, psnr in scenes.items()]
    entries = [bundle_entry(r, record, tmp / "results" / "x" / r["scene"] / "report.md", tmp) for r in rows]
    return record, entries


def _readme(tmp: Path) -> Path:
    readme = tmp / "README.md"
    readme.write_text(f"intro\n\n{BEGIN}\nold table\n{END}\n\nrest\n")
    return readme


def test_a_run_of_one_scene_replaces_its_row_and_keeps_the_others(tmp_path: Path) -> None:
    readme = _readme(tmp_path)
    _, first = _run(tmp_path, {"plume_time": 33.5, "tangle_iso": 30.0, "vortex_tf1": 43.8, "cosmo_sim": 40.2}, 10, "a",
                    (3, 11, 25))
    write_bundle_record(tmp_path / "results", tmp_path, first, readme)
    _, second = _run(tmp_path, {"tangle_iso": 32.4}, 30, "b")
    record = write_bundle_record(tmp_path / "results", tmp_path, second, readme)

    by_scene = {e["scene"]: e for e in record["scenes"]}
    assert [e["scene"] for e in record["scenes"]] == ["plume_time", "tangle_iso", "vortex_tf1", "cosmo_sim"]
    assert (by_scene["tangle_iso"]["psnr"], by_scene["tangle_iso"]["minutes"], by_scene["tangle_iso"]["command"]) == (
        32.4, 30, "b")
    assert (by_scene["plume_time"]["psnr"], by_scene["plume_time"]["minutes"], by_scene["plume_time"]["command"]) == (
        33.5, 10, "a")
    assert json.loads((tmp_path / "results" / "bundled_eval" / "bundled.json").read_text()) == record

    text = readme.read_text()
    assert "old table" not in text and text.startswith("intro\n") and text.endswith("\nrest\n")
    assert "| `tangle_iso` | isovalue (ir) | 30 | 32.40 | 0.970 | 2.20 | [report](results/x/tangle_iso/report.md) |" in text
    index = (tmp_path / "results" / "bundled_eval" / "README.md").read_text()
    assert "[report](../x/plume_time/report.md)" in index and "trained by `b`" in index
    # each row says which views its run trained on: the new one every view, the kept ones their hold-out
    assert by_scene["tangle_iso"]["holdout_views"] == [] and by_scene["plume_time"]["holdout_views"] == [3, 11, 25]
    lines = {line.split("`")[1]: line for line in index.splitlines() if line.startswith("- `")}
    assert lines["tangle_iso"].endswith(" min on every view.")
    assert lines["plume_time"].endswith(" min, views 3, 11, 25 held out.")


def test_refusals_change_nothing(tmp_path: Path) -> None:
    readme = _readme(tmp_path)
    _, entries = _run(tmp_path, {"tangle_iso": 30.0}, 10, "a")
    write_bundle_record(tmp_path / "results", tmp_path, entries, readme)
    saved = (tmp_path / "results" / "bundled_eval" / "bundled.json").read_text()

    _, other = _run(tmp_path, {"vortex_tf2": 39.0}, 10, "b")
    with pytest.raises(ValueError, match="vortex_tf2"):
        write_bundle_record(tmp_path / "results", tmp_path, other, readme)
    with pytest.raises(ValueError, match="lacks"):
        bundle_entry({"scene": "tangle_iso", "psnr": 1.0}, {}, tmp_path / "r.md", tmp_path)
    assert (tmp_path / "results" / "bundled_eval" / "bundled.json").read_text() == saved
