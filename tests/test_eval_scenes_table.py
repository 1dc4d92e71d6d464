"""bench/eval_scenes.py's results table: the details list every row rerun since the record, grouped by
day, CPU and command, the CPU only where it is not the record's."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import eval_scenes  # noqa: E402

RECORD_CPU = "Xeon (AMX bf16)"


def row(scene: str, rerun: dict | None = None) -> dict:
    return {"scene": scene, "kind": "dvr", "K": 1, "psnr": 30.0, "ssim": 0.95, "iterations": 10,
            "resolution": [8, 8, 8], "ms_per_frame": 5.0, "model_mb": 1.0, "paper": None, "rerun": rerun}


def record() -> dict:
    return {"machine": {"cpu": RECORD_CPU}, "scenes": [
        row("a", {"date": "2026-11-27 03:00:00 UTC", "cpu": RECORD_CPU, "command": "x --scenes a", "rescored": True}),
        row("b", {"date": "2026-11-27 04:00:00 UTC", "cpu": RECORD_CPU, "command": "x --scenes b", "rescored": True}),
        row("c", {"date": "2026-11-29 08:00:00 UTC", "cpu": "EPYC", "command": "x --scenes c"}),
        row("d"),
    ]}


def notes(lines: list[str]) -> list[str]:
    return [line for line in lines if "Rerun" in line]


def bullets(lines: list[str]) -> list[str]:
    return [line for line in lines if line.startswith("- ")]


def test_the_details_list_each_reruns_command() -> None:
    lines = eval_scenes.table_lines(record())
    assert len(notes(lines)) == 1
    assert bullets(lines) == ["- a (2026-11-27, `x --scenes a`, evaluated again, not retrained)",
                              "- b (2026-11-27, `x --scenes b`, evaluated again, not retrained)",
                              "- c (2026-11-29, EPYC, `x --scenes c`)"]


def test_no_note_without_a_rerun() -> None:
    rec = record()
    rec["scenes"] = [row("d")]
    assert notes(eval_scenes.table_lines(rec)) == []
    assert not any("record's" in line for line in eval_scenes.table_lines(rec))
