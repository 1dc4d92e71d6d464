"""``visnerf eval`` on a tiny checkpoint and a tiny K=2 scene: every section, finite numbers, clear errors."""

import json
import math
import shutil
from pathlib import Path

import pytest
import torch

from visnerf.cli import main
from visnerf.evaluation.perceptual import LpipsConfig, load_lpips
from visnerf.testing import make_tiny_checkpoint


@pytest.fixture(autouse=True)
def one_thread(monkeypatch):
    monkeypatch.setenv("VISNERF_THREADS", "1")  # `pick_device` sets the thread count from it


def _numbers(value, path="summary"):
    """Every number in a JSON document, with where it is."""
    if isinstance(value, bool):
        return
    if isinstance(value, int | float):
        yield path, value
    elif isinstance(value, dict):
        for k, v in value.items():
            yield from _numbers(v, f"{path}.{k}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _numbers(v, f"{path}[{i}]")


@pytest.fixture(scope="module")
def report(tiny_eval, tmp_path_factory):
    ckpt, data = tiny_eval
    out = tmp_path_factory.mktemp("report")
    code = main(["eval", str(ckpt), str(data), "--out", str(out), "--device", "cpu", "--sweep-frames", "2"])
    assert code == 0
    return out, json.loads((out / "summary.json").read_text())


@pytest.mark.slow
def test_report_has_every_section_with_finite_numbers(report):
    out, s = report
    for path, value in _numbers(s):
        assert math.isfinite(value), path
    m = s["metrics"]
    assert m["n"] == 12 and 20.0 < m["psnr"] < 60.0 and 0.0 < m["ssim"] <= 1.0 and m["ms_median"] > 0
    assert m["lpips"] is None and "not computed" not in m["lpips_note"] and "weights" in m["lpips_note"]

    groups = s["parameter_space"]["groups"]
    for name in ("at_training_values", "between_training_values", "one_moving", "all_moving"):
        assert groups[name]["n"] > 0 and math.isfinite(groups[name]["psnr"]), name
    assert groups["at_training_values"]["n"] + groups["between_training_values"]["n"] == 12

    diffs = s["differences"]
    assert diffs["space"].startswith("CIELUV") and len(diffs["frames"]) == 3
    for f in diffs["frames"]:
        assert all((out / p).is_file() for p in f["images"].values()) and (out / f["figure"]).is_file()
        assert 0.0 < f["delta_e_mean"] <= f["delta_e_max"]

    sweep = s["render_sweep"]
    names = {p["name"] for p in sweep["points"]}
    assert {"full (checkpoint settings)", "preview quality", "no early termination", "scale 0.5"} <= names
    assert any(p.startswith("step ") for p in names) and any(p["on_front"] for p in sweep["points"])
    assert (out / sweep["figure"]).is_file() and (out / sweep["data"]).is_file()

    training = s["training"]
    assert len(training["runs"]) == 1 and training["runs"][0]["metric"] == "val_psnr"
    assert training["runs"][0]["final_psnr"] == pytest.approx(16.4)  # last logged row: 14 + 0.8 * 3
    assert (out / training["figure"]).is_file() and (out / training["data"]).is_file()

    md = (out / "report.md").read_text()
    for heading in ("## Summary", "## Error by place in parameter space", "## Difference images (CIELUV)",
                    "## Error against render time", "## Error against training time"):
        assert heading in md
    assert "LPIPS: not computed" in md
    rows = (out / "frames.csv").read_text().splitlines()
    assert len(rows) == 13 and rows[0].startswith("frame,file,a,b,") and "render_ms" in rows[0]
    for figure in ("psnr_per_frame", "render_sweep", "training_curves", "difference_legend"):
        assert (out / "figures" / f"{figure}.png").stat().st_size > 1000


def test_other_runs_logs_are_plotted_together(tiny_eval, tmp_path):
    ckpt, data = tiny_eval
    other = tmp_path / "other.log.json"
    other.write_text(json.dumps([{"iteration": 10, "train_seconds": 5.0, "wall_seconds": 6.0, "train_psnr": 12.0}]))
    out = tmp_path / "r"
    assert main(["eval", str(ckpt), str(data), "--out", str(out), "--device", "cpu", "--no-sweep",
                 "--max-frames", "3", "--train-log", str(other)]) == 0
    s = json.loads((out / "summary.json").read_text())
    runs = {r["name"]: r for r in s["training"]["runs"]}
    assert set(runs) == {"tiny", "other"} and runs["other"]["metric"] == "train_psnr"
    assert s["metrics"]["n"] == 3 and s["render_sweep"]["points"] == []


def test_lpips_without_local_weights_is_null_with_reason(tmp_path):
    scorer, why = load_lpips(LpipsConfig(weights=None), torch.device("cpu"))
    assert scorer is None and "--lpips-weights" in why
    scorer, why = load_lpips(LpipsConfig(weights=tmp_path / "alex.pth"), torch.device("cpu"))
    assert scorer is None and "does not exist" in why


def _eval_fails(capsys, ckpt: Path, data: Path, out: Path, *extra: str) -> str:
    assert main(["eval", str(ckpt), str(data), "--out", str(out), "--device", "cpu", *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ")
    return err


def test_missing_ground_truth_image_is_named(tiny_eval, tmp_path, capsys):
    ckpt, data = tiny_eval
    broken = tmp_path / "data"
    shutil.copytree(data, broken)
    (broken / "test" / "r_3.png").unlink()
    err = _eval_fails(capsys, ckpt, broken, tmp_path / "out")
    assert "frame 3 (./test/r_3)" in err and "not found" in err


def test_missing_split_names_the_file(tiny_eval, tmp_path, capsys):
    ckpt, data = tiny_eval
    err = _eval_fails(capsys, ckpt, data, tmp_path / "out", "--split", "val")
    assert "transforms_val.json" in err and "transforms_test.json" in err


@pytest.mark.parametrize(
    "axes, message",
    [
        ([("a", [0.0, 1.0]), ("c", [0.0, 1.0])], "the dataset lacks ['c']"),
        ([("a", [0.0, 1.0])], "the dataset varies ['b']"),
        ([("a", [0.0, 0.5]), ("b", [0.0, 0.5, 1.0])], "outside the checkpoint's range"),
    ],
)
def test_checkpoint_whose_axes_do_not_match_the_dataset(tiny_eval, tmp_path, capsys, axes, message):
    _, data = tiny_eval
    ckpt = make_tiny_checkpoint(tmp_path / "other.safetensors", axes)
    err = _eval_fails(capsys, ckpt, data, tmp_path / "out")
    assert message in err
    assert not (tmp_path / "out" / "summary.json").exists()


def test_bad_checkpoint_is_a_clear_error(tiny_eval, tmp_path, capsys):
    _, data = tiny_eval
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a checkpoint")
    assert "safetensors" in _eval_fails(capsys, bad, data, tmp_path / "out")


def test_a_report_written_again_keeps_only_its_own_examples(tiny_eval, tmp_path):
    ckpt, data = tiny_eval
    out = tmp_path / "report"
    (out / "figures").mkdir(parents=True)
    (out / "images").mkdir()
    earlier = [out / "figures" / "difference_frame_9999.png", out / "images" / "frame_9999_synth.png"]
    kept = [out / "figures" / "notes.png", out / "own.txt"]  # not names the writer gives
    for path in earlier + kept:
        path.write_bytes(b"x")
    assert main(["eval", str(ckpt), str(data), "--out", str(out), "--device", "cpu", "--no-sweep"]) == 0
    assert not any(path.exists() for path in earlier)
    assert all(path.exists() for path in kept)
    text = (out / "report.md").read_text()
    examples = [*(out / "figures").glob("difference_frame_*.png"), *(out / "images").glob("frame_*_*.png")]
    assert examples and all(path.relative_to(out).as_posix() in text for path in examples)
