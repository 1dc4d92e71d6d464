"""``visnerf make-scene`` and ``visnerf scenes``: arguments, refusals and the dataset written."""

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from visnerf.scenes import commands
from visnerf.scenes.catalog import get_scene, scene_catalog
from visnerf.scenes.writer import DatasetOptions, write_scene

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # small renders: one thread (conftest)


def _run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="visnerf")
    commands.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.mark.parametrize(
    "extra, message",
    [
        (["no_such_scene"], "unknown scene"),
        (["tangle_static", "--res", "4"], "--res"),
        (["tangle_static", "--views", "0"], "--views"),
    ],
)
def test_bad_input_exits_2_and_writes_nothing(tmp_path: Path, capsys, extra: list[str], message: str) -> None:
    out = tmp_path / "out"
    assert _run(["make-scene", *extra, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_non_empty_output_needs_force(tmp_path: Path, capsys) -> None:
    (tmp_path / "keep.txt").write_text("mine")
    assert _run(["make-scene", "tangle_static", "--out", str(tmp_path), "--res", "8"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]


def test_make_scene_writes_a_complete_dataset(tmp_path: Path) -> None:
    out = tmp_path / "vortex"
    argv = [
        "make-scene",
        "vortex_tf1",
        "--out",
        str(out),
        "--res",
        "12",
        "--views",
        "12",
        "--test-views",
        "4",
    ]
    assert _run([*argv, "--quiet"]) == 0
    train = json.loads((out / "transforms_train.json").read_text())
    test = json.loads((out / "transforms_test.json").read_text())
    assert train["camera_angle_x"] == pytest.approx(np.radians(30.0))
    assert train["param_names"] == ["opacity_low", "opacity_high"] and train["white_background"] is True
    assert train["bbox"] == [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]]
    assert train["scene"]["name"] == "vortex_tf1" and train["scene"]["kind"] == "dvr"
    assert len(train["frames"]) == 12 * 9 and len(test["frames"]) == 4
    low, high = get_scene("vortex_tf1").axes
    assert {tuple(f["params"]) for f in train["frames"]} == {
        (a, b) for a in low.values() for b in high.values()
    }
    for frame in train["frames"][:3] + test["frames"]:
        c2w = np.array(frame["transform_matrix"])
        assert c2w.shape == (4, 4) and np.allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3))
        image = Image.open(out / f"{frame['file_path']}.png")
        assert image.mode == "RGB" and image.size == (12, 12)
    assert set(test["frames"][0]["view"]) >= {"azimuth", "elevation"}
    assert not list(out.glob(".*.tmp"))
    # --force replaces the dataset
    assert _run(["make-scene", "tangle_static", "--out", str(out), "--res", "8", "--views", "12",
                 "--test-views", "2", "--force", "--quiet"]) == 0  # fmt: skip
    replaced = json.loads((out / "transforms_train.json").read_text())
    assert replaced["param_names"] == [] and all(f["params"] == [] for f in replaced["frames"])
    assert len(list((out / "train").glob("r_*.png"))) == 12


def test_scenes_lists_every_scene_with_its_parameters(capsys) -> None:
    assert _run(["scenes"]) == 0
    text = capsys.readouterr().out
    assert all(name in text for name in scene_catalog())
    assert _run(["scenes", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    by_name = {s["name"]: s for s in listed}
    assert [p["name"] for p in by_name["cosmo_sim"]["params"]] == ["omega_m", "omega_b", "hubble"]
    assert by_name["plume_static"]["params"] == [] and by_name["tangle_iso"]["kind"] == "ir"
    counts = {name: len(s["params"]) for name, s in by_name.items()}
    assert counts["plume_time"] == 1 and counts["vortex_tf1"] == 2 and counts["vortex_tf2"] == 1


@pytest.mark.slow
def test_worker_processes_write_the_same_images(tmp_path: Path) -> None:
    """Two render processes give byte-identical images to one (each image is rendered alone)."""
    options = DatasetOptions(resolution=10, n_views=12, n_test_views=2)
    write_scene(get_scene("vortex_static"), tmp_path / "serial", options, progress=False)
    write_scene(get_scene("vortex_static"), tmp_path / "parallel", options, progress=False, workers=2)
    for split, count in (("train", 12), ("test", 2)):
        for i in range(count):
            a = np.asarray(Image.open(tmp_path / "serial" / split / f"r_{i}.png"))
            b = np.asarray(Image.open(tmp_path / "parallel" / split / f"r_{i}.png"))
            assert np.array_equal(a, b)
    serial = json.loads((tmp_path / "serial" / "transforms_train.json").read_text())
    assert serial == json.loads((tmp_path / "parallel" / "transforms_train.json").read_text())
