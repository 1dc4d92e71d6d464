"""``--holdout-value AXIS=VALUE`` of ``visnerf train`` and ``visnerf calibrate``: what the parser
reads, what it refuses with a message, and how the axis resolves against a dataset."""

import argparse
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from visnerf import cli
from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.data.scene import SceneData, axes_from_values
from visnerf.holdout_options import holdout_config, parse_axis_value


def _scene() -> SceneData:
    """Two views at each of the 3 x 2 settings of (OmM, h)."""
    settings = [(a, h) for a in (0.12, 0.1375, 0.155) for h in (0.55, 0.85)]
    values = torch.tensor([s for s in settings for _ in range(2)], dtype=torch.float64)
    _, axes = axes_from_values(["OmM", "h"], values.numpy())
    n = values.shape[0]
    return SceneData(images=torch.zeros(n, 2, 2, 3, dtype=torch.uint8), c2w=torch.eye(4).expand(n, 4, 4).clone(),
                     intrinsics=Intrinsics.from_fov(2, 2, math.radians(30.0)), params=values.float(),
                     param_axes=axes, view_ids=torch.arange(n) % 2)


@pytest.mark.parametrize(
    ("text", "expected"),
    [("OmM=0.1375", ("OmM", 0.1375)), ("0=0.1375", ("0", 0.1375)), (" h = 0.7 ", ("h", 0.7)), ("x=-1e-3", ("x", -1e-3))],
)
def test_reads_axis_and_value(text: str, expected: tuple[str, float]) -> None:
    assert parse_axis_value(text) == expected


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("0.1375", r"cannot read held-out axis value '0.1375': use AXIS=VALUE"),
        ("=0.1375", r"cannot read held-out axis value '=0.1375': use AXIS=VALUE"),
        ("OmM=", r"held-out axis value 'OmM=': '' is not a finite number"),
        ("OmM=middle", r"held-out axis value 'OmM=middle': 'middle' is not a finite number"),
        ("OmM=nan", r"held-out axis value 'OmM=nan': 'nan' is not a finite number"),
        ("OmM=inf", r"held-out axis value 'OmM=inf': 'inf' is not a finite number"),
    ],
)
def test_refuses_naming_the_problem(text: str, message: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match=message):
        parse_axis_value(text)


@pytest.mark.parametrize("command", [["train", "data", "--out", "m.safetensors"], ["calibrate", "m.safetensors", "data"]])
def test_the_flag_repeats_and_resolves_names_and_indices(command: list[str]) -> None:
    args = cli.build_parser().parse_args([*command, "--holdout-views", "1", "--holdout-value", "OmM=0.1375",
                                          "--holdout-value", "1=0.85"])
    assert args.holdout_value == [("OmM", 0.1375), ("1", 0.85)]
    holdout = holdout_config(_scene(), args)
    assert holdout.views == (1,) and holdout.axis_values == ((0, 0.1375), (1, 0.85))
    assert cli.build_parser().parse_args(command).holdout_value == []


def test_an_unknown_axis_name_is_named_with_the_datasets_axes() -> None:
    args = cli.build_parser().parse_args(["train", "data", "--out", "m.safetensors", "--holdout-value", "OmB=0.0225"])
    with pytest.raises(ValueError, match=r"no parameter axis 'OmB': this dataset's varying parameters are 0 'OmM', 1 'h'"):
        holdout_config(_scene(), args)


def test_a_malformed_flag_stops_the_parser(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["train", "data", "--out", "m.safetensors", "--holdout-value", "OmM"])
    assert "cannot read held-out axis value 'OmM': use AXIS=VALUE" in capsys.readouterr().err


def _write_dataset(folder: Path) -> None:
    """Two 8x8 views at each of three values of ``a`` (``b`` constant, so dropped)."""
    (folder / "train").mkdir(parents=True)
    frames = []
    for i, (a, view) in enumerate((a, v) for a in (0.1, 0.2, 0.3) for v in range(2)):
        Image.fromarray(np.full((8, 8, 3), 40 * i, dtype=np.uint8)).save(folder / "train" / f"r_{i}.png")
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": orbit_c2w(90.0 * view, 20.0, 2.0).tolist(),
                       "params": [a, 0.5]})
    meta = {"camera_angle_x": math.radians(40.0), "param_names": ["a", "b"], "frames": frames}
    (folder / "transforms_train.json").write_text(json.dumps(meta))


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("b=0.5", "no parameter axis 'b': this dataset's varying parameters are 0 'a'"),
        ("1=0.5", r"axis 1 does not exist; this dataset has 1 varying parameter, axes 0 to 0 \(a\)"),
        ("a=0.1", "the hold-out leaves a parameter axis with a single training value"),
    ],
)
def test_train_names_a_bad_held_out_axis_before_it_trains(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                          value: str, message: str) -> None:
    _write_dataset(tmp_path / "data")
    out = tmp_path / "m.safetensors"
    code = cli.main(["train", str(tmp_path / "data"), "--out", str(out), "--holdout-value", value,
                     "--holdout-value", "a=0.3", "--device", "cpu", "--quiet"])
    assert code == 2
    assert re.search(message, capsys.readouterr().err)
    assert not out.exists()
