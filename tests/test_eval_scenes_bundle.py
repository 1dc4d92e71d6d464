"""bench/eval_scenes.py --bundle: the bundled scenes train on every view, as `visnerf train DATA` does,
and a bundling run never replaces the record's rows, which hold views out."""

import csv
import json
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import eval_scenes  # noqa: E402


@pytest.mark.slow
def test_a_bundling_run_trains_the_bundled_scene_on_every_view(tmp_path: Path) -> None:
    bundle, results = tmp_path / "checkpoints", tmp_path / "results"
    code = eval_scenes.main(["--scenes", "tangle_iso", "--minutes-per-scene", "0.1", "--res", "16", "--test-views", "2",
                             "--sweep-frames", "1", "--threads", "1", "--bundle", str(bundle), "--results", str(results),
                             "--data-root", str(tmp_path / "data")])
    assert code == 0
    row = json.loads((results / "eval_scenes.partial.json").read_text())["scenes"][0]
    assert row["scene"] == "tangle_iso" and row["holdout_views"] == []
    # nothing held out: the training log has no validation figure at any row
    with (bundle / "tangle_iso.log.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert rows and all(not math.isfinite(float(r.get("val_psnr") or "nan")) for r in rows)
    assert (bundle / "tangle_iso.safetensors").stat().st_size > 0
    entry = json.loads((results / "bundled_eval" / "bundled.json").read_text())["scenes"][0]
    assert entry["holdout_views"] == []
    index = (results / "bundled_eval" / "README.md").read_text()
    assert "min on every view." in index


def test_bundling_and_replacing_the_record_rows_together_is_refused(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    results = tmp_path / "results"
    results.mkdir()
    # a record the run would match (a small one, so that code without the refusal fails fast)
    record = {"resolution": 16, "test_views": 2, "minutes_per_scene": 0.02, "scenes": []}
    (results / "eval_scenes.json").write_text(json.dumps(record))
    with pytest.raises(SystemExit) as exit_info:
        eval_scenes.main(["--scenes", "tangle_iso", "--bundle", str(tmp_path / "checkpoints"), "--replace-rows",
                          "--res", "16", "--test-views", "2", "--minutes-per-scene", "0.02",
                          "--results", str(results), "--data-root", str(tmp_path / "data")])
    assert exit_info.value.code == 2
    assert "every view" in capsys.readouterr().err
    assert sorted(p.name for p in results.iterdir()) == ["eval_scenes.json"]
    assert not (tmp_path / "checkpoints").exists()


def test_bundling_in_a_full_run_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A run of every scene is the record's; the bundled ones would train another way in it."""
    with pytest.raises(SystemExit) as exit_info:
        eval_scenes.main(["--bundle", str(tmp_path / "checkpoints"), "--results", str(tmp_path / "results"),
                          "--data-root", str(tmp_path / "data")])
    assert exit_info.value.code == 2
    assert "name the scenes" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
