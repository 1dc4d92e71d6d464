"""Bad datasets are refused with the problem and the frame(s) named, before anything is written."""

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from visnerf.cli import main
from visnerf.data.cameras import orbit_c2w
from visnerf.data.datasets import DatasetError, load_dataset

N_FRAMES = 3
SIZE = 8

Meta = dict[str, Any]
Breakage = Callable[[Path, Meta], None]


def _write_png(path: Path, width: int = SIZE, height: int = SIZE, seed: int = 0) -> None:
    """A noisy RGB PNG (noise keeps the file long enough to truncate mid-data)."""
    pixels = np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(path)


def _write_meta(folder: Path, meta: Meta) -> None:
    (folder / "transforms_train.json").write_text(json.dumps(meta))  # NaN/inf as Python json writes and reads them


def _make_dataset(folder: Path, pose_noise: float = 0.0) -> Meta:
    """``N_FRAMES`` 8x8 frames of cameras at distance 2 orbiting the origin, two parameters each."""
    (folder / "train").mkdir(parents=True)
    rng = np.random.default_rng(1)
    frames = []
    for i in range(N_FRAMES):
        _write_png(folder / "train" / f"r_{i}.png", seed=i)
        c2w = orbit_c2w(120.0 * i, 20.0, 2.0) + pose_noise * rng.standard_normal((4, 4))
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": c2w.tolist(), "params": [0.1 * i, 0.5]})
    meta = {"camera_angle_x": math.radians(40.0), "param_names": ["a", "b"], "frames": frames}
    _write_meta(folder, meta)
    return meta


def _pose(meta: Meta, frame: int) -> np.ndarray:
    return np.asarray(meta["frames"][frame]["transform_matrix"], dtype=np.float64)


def _set_pose(meta: Meta, frame: int, c2w: np.ndarray) -> None:
    meta["frames"][frame]["transform_matrix"] = c2w.tolist()


def _missing_image(folder: Path, meta: Meta) -> None:
    (folder / "train" / "r_1.png").unlink()


def _not_an_image(folder: Path, meta: Meta) -> None:
    (folder / "train" / "r_1.png").write_bytes(b"this is not an image")


def _truncated_png(folder: Path, meta: Meta) -> None:
    path = folder / "train" / "r_2.png"
    path.write_bytes(path.read_bytes()[:80])


def _different_size(folder: Path, meta: Meta) -> None:
    _write_png(folder / "train" / "r_2.png", width=16, height=8)


def _nan_in_pose(folder: Path, meta: Meta) -> None:
    meta["frames"][1]["transform_matrix"][0][3] = float("nan")


def _pose_not_4x4(folder: Path, meta: Meta) -> None:
    meta["frames"][1]["transform_matrix"] = meta["frames"][1]["transform_matrix"][:3]


def _scaled_rotation(folder: Path, meta: Meta) -> None:
    c2w = _pose(meta, 1)
    c2w[:3, :3] *= 1.5
    _set_pose(meta, 1, c2w)


def _sheared_rotation(folder: Path, meta: Meta) -> None:
    c2w = _pose(meta, 1)
    c2w[:3, 1] += 0.3 * c2w[:3, 0]
    _set_pose(meta, 1, c2w)


def _mirrored_rotation(folder: Path, meta: Meta) -> None:
    c2w = _pose(meta, 1)
    c2w[:3, 0] *= -1.0
    _set_pose(meta, 1, c2w)


def _bad_last_row(folder: Path, meta: Meta) -> None:
    meta["frames"][2]["transform_matrix"][3] = [0.0, 0.0, 0.5, 1.0]


def _params_of_different_lengths(folder: Path, meta: Meta) -> None:
    meta["frames"][2]["params"] = [0.3]


def _non_finite_param(folder: Path, meta: Meta) -> None:
    meta["frames"][1]["params"] = [float("inf"), 0.5]


def _non_numeric_param(folder: Path, meta: Meta) -> None:
    meta["frames"][1]["params"] = ["high", 0.5]


def _duplicated_frame(folder: Path, meta: Meta) -> None:
    meta["frames"][2]["file_path"] = "./train/r_0"


def _duplicated_frame_spelled_differently(folder: Path, meta: Meta) -> None:
    meta["frames"][2]["file_path"] = "train/r_0.png"


def _empty_frames(folder: Path, meta: Meta) -> None:
    meta["frames"] = []


def _frames_not_a_list(folder: Path, meta: Meta) -> None:
    meta["frames"] = {"0": meta["frames"][0]}


def _missing_pose(folder: Path, meta: Meta) -> None:
    del meta["frames"][1]["transform_matrix"]


BAD_CASES: list[tuple[str, Breakage, list[str]]] = [
    ("missing image", _missing_image, ["frame 1 (./train/r_1): image not found"]),
    ("not an image", _not_an_image, ["frame 1 (./train/r_1): cannot decode image", "r_1.png"]),
    ("truncated png", _truncated_png, ["frame 2 (./train/r_2): cannot decode image", "r_2.png"]),
    ("different sizes", _different_size,
     ["images differ in size", "frame 2 (./train/r_2) is 16x8", "frame 0 (./train/r_0) is 8x8"]),
    ("nan in pose", _nan_in_pose, ["frame 1 (./train/r_1): transform_matrix has non-finite entries"]),
    ("pose not 4x4", _pose_not_4x4, ["frame 1 (./train/r_1): transform_matrix is not a 4x4 matrix (shape [3, 4])"]),
    ("scaled rotation", _scaled_rotation,
     ["frame 1 (./train/r_1): transform_matrix rotation is not orthonormal", "column lengths 1.5, 1.5, 1.5"]),
    ("sheared rotation", _sheared_rotation, ["frame 1 (./train/r_1): transform_matrix rotation is not orthonormal"]),
    ("mirrored rotation", _mirrored_rotation, ["frame 1 (./train/r_1): transform_matrix rotation has determinant -1"]),
    ("bad last row", _bad_last_row,
     ["frame 2 (./train/r_2): transform_matrix last row is [0.0, 0.0, 0.5, 1.0], expected [0, 0, 0, 1]"]),
    ("params of different lengths", _params_of_different_lengths,
     ["frames disagree on the number of parameters", "frame 2 (./train/r_2) has 1", "frame 0 (./train/r_0) has 2"]),
    ("non-finite param", _non_finite_param, ["frame 1 (./train/r_1): parameter values must be finite"]),
    ("non-numeric param", _non_numeric_param, ["frame 1 (./train/r_1): params must be numbers"]),
    ("duplicated frame", _duplicated_frame,
     ["frame 0 (./train/r_0) and frame 2 (./train/r_0) use the same image", "a frame appears twice"]),
    ("duplicated frame, other spelling", _duplicated_frame_spelled_differently,
     ["frame 0 (./train/r_0) and frame 2 (train/r_0.png) use the same image"]),
    ("empty frames list", _empty_frames, ["has no frames (the 'frames' list is empty)"]),
    ("frames not a list", _frames_not_a_list, ["'frames' must be a list of frames, got dict"]),
    ("missing pose", _missing_pose, ["frame 1 (./train/r_1) lacks 'transform_matrix'"]),
]


def _broken_dataset(folder: Path, breakage: Breakage) -> Path:
    meta = _make_dataset(folder)
    breakage(folder, meta)
    _write_meta(folder, meta)
    return folder


@pytest.mark.parametrize(("breakage", "expected"), [case[1:] for case in BAD_CASES], ids=[c[0] for c in BAD_CASES])
def test_bad_dataset_is_refused_naming_the_problem(tmp_path: Path, breakage: Breakage, expected: list[str]) -> None:
    folder = _broken_dataset(tmp_path / "data", breakage)
    with pytest.raises(DatasetError) as caught:
        load_dataset(folder, "train")
    message = str(caught.value)
    assert "transforms_train.json" in message
    for words in expected:
        assert words in message


def test_valid_dataset_with_float_noise_in_poses_loads(tmp_path: Path) -> None:
    folder = tmp_path / "data"
    meta = _make_dataset(folder, pose_noise=1e-6)
    scene = load_dataset(folder, "train")
    assert scene.n_frames == N_FRAMES
    assert tuple(scene.images.shape) == (N_FRAMES, SIZE, SIZE, 3)
    assert np.allclose(scene.c2w.numpy(), [f["transform_matrix"] for f in meta["frames"]], atol=1e-6)
    assert [axis.name for axis in scene.param_axes] == ["a"]  # b is constant


@pytest.mark.parametrize(
    ("breakage", "expected"),
    [
        (_scaled_rotation, "transform_matrix rotation is not orthonormal"),
        (_different_size, "images differ in size: frame 2 (./train/r_2) is 16x8"),
        (_duplicated_frame, "use the same image"),
    ],
    ids=["scaled rotation", "different sizes", "duplicated frame"],
)
def test_train_refuses_bad_dataset_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], breakage: Breakage, expected: str
) -> None:
    folder = _broken_dataset(tmp_path / "data", breakage)
    out = tmp_path / "model.safetensors"
    code = main(["train", str(folder), "--out", str(out), "--device", "cpu", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("error: ") and expected in err
    assert not out.exists()
    assert not out.with_suffix(".log.csv").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]
