"""Frames that carry both ``time`` and ``params`` (D-NeRF / ViSNeRF style): one reader names the
axes for training and evaluation alike, so a model can be scored on its own test split."""

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from visnerf.data.cameras import orbit_c2w
from visnerf.data.datasets import DatasetError, read_split
from visnerf.evaluation.ground_truth import load_ground_truth


def _dataset(folder: Path, frames_of: dict[str, list[dict]], names: list[str] | None = None) -> Path:
    for split, extra in frames_of.items():
        (folder / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for i, fields in enumerate(extra):
            Image.fromarray(np.full((4, 4, 3), 40 * i, dtype=np.uint8)).save(folder / split / f"r_{i}.png")
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": orbit_c2w(30.0 * i, 10.0, 2.0).tolist(),
                           **fields})
        meta = {"camera_angle_x": 0.6, "frames": frames, **({"param_names": names} if names else {})}
        (folder / f"transforms_{split}.json").write_text(json.dumps(meta))
    return folder


def test_time_repeated_in_params_names_that_column_time(tmp_path) -> None:
    rows = [{"time": t, "params": [t, x]} for t, x in ((0.0, 1.0), (0.5, 2.0), (1.0, 1.0))]
    data = _dataset(tmp_path / "d", {"train": rows, "test": [{"time": 0.25, "params": [0.25, 1.5]}]})
    parsed = read_split(data, "train")
    assert parsed.param_names == ("time", "p1")
    assert [a.name for a in parsed.scene.param_axes] == ["time", "p1"]
    truth = load_ground_truth(data, "test", parsed.scene.param_axes)
    assert truth.params.tolist() == [[0.25, 1.5]]


def test_time_beside_other_params_is_an_axis_of_its_own(tmp_path) -> None:
    rows = [{"time": t, "params": [x]} for t, x in ((0.0, 5.0), (1.0, 6.0), (2.0, 5.0))]
    data = _dataset(tmp_path / "d", {"train": rows, "test": [{"time": 1.5, "params": [5.5]}]}, names=["OmM"])
    parsed = read_split(data, "train")
    assert parsed.param_names == ("OmM", "time")
    truth = load_ground_truth(data, "test", parsed.scene.param_axes)
    assert truth.params.tolist() == [[5.5, 1.5]]


def test_time_alone_is_the_time_axis(tmp_path) -> None:
    data = _dataset(tmp_path / "d", {"train": [{"time": t} for t in (0.0, 0.5, 1.0)]})
    assert read_split(data, "train").param_names == ("time",)


def test_param_names_of_the_wrong_length_are_refused(tmp_path) -> None:
    rows = [{"time": t, "params": [t, 1.0]} for t in (0.0, 1.0)]
    data = _dataset(tmp_path / "d", {"train": rows}, names=["a", "b", "c", "d"])
    with pytest.raises(DatasetError, match="param_names has 4 names for 2 parameters and a time"):
        read_split(data, "train")
