"""Cinema databases: the producers' camera conventions against independent references, the writer
and the reader against the reference renderer's ground truth, and every refusal."""

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from visnerf.cli import main
from visnerf.data.cameras import orbit_c2w
from visnerf.data.datasets import DatasetError, has_split, load_dataset, read_split
from visnerf.data.parsers.cinema_cameras import (
    CinemaCamera,
    ascent_angles,
    ascent_c2w,
    paraview_c2w,
)
from visnerf.evaluation.ground_truth import EvaluationError, load_ground_truth
from visnerf.scenes.catalog import get_scene
from visnerf.scenes.writer import DatasetOptions, plan_frames

RES, VIEWS, TEST_VIEWS = 16, 4, 3


def _rotate(v: np.ndarray, axis: np.ndarray, deg: float) -> np.ndarray:
    """Rodrigues' rotation of ``v`` about unit ``axis`` by ``deg`` (right-handed)."""
    a, k = math.radians(deg), axis / np.linalg.norm(axis)
    return v * math.cos(a) + np.cross(k, v) * math.sin(a) + k * (k @ v) * (1 - math.cos(a))


def _vtk_phi_theta(phi: float, theta: float, focal: np.ndarray, d: float, steps: int = 720) -> np.ndarray:
    """VTK's camera moves as ParaView's extractor applies them: Azimuth(phi) about the view up through
    the focal point, then Elevation(theta) in small steps about -(right), the view up kept and
    orthogonalised after each step (vtkCamera::OrthogonalizeViewUp)."""
    pos, up = focal + np.array([0.0, 0.0, d]), np.array([0.0, 1.0, 0.0])
    pos = focal + _rotate(pos - focal, up, phi)
    for _ in range(steps):
        dop = (focal - pos) / np.linalg.norm(focal - pos)
        right = np.cross(dop, up)
        pos = focal + _rotate(pos - focal, -right, theta / steps)
        dop = (focal - pos) / np.linalg.norm(focal - pos)
        up = up - (up @ dop) * dop
        up /= np.linalg.norm(up)
    dop = (focal - pos) / np.linalg.norm(focal - pos)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = np.cross(dop, up), up, -dop, pos
    return c2w


@pytest.mark.parametrize(("phi", "theta"), [(0.0, 0.0), (60.0, 30.0), (-150.0, 75.0), (200.0, 120.0), (30.0, 250.0), (-45.0, -60.0)])
def test_paraview_convention_matches_vtk_camera_moves(phi, theta) -> None:
    focal = np.array([0.3, -0.2, 0.5])
    assert np.allclose(paraview_c2w(phi, theta, tuple(focal), 2.5), _vtk_phi_theta(phi, theta, focal, 2.5), atol=1e-6)


@pytest.mark.parametrize(("phi", "theta"), [(0.0, 0.0), (-180.0, 45.0), (30.0, 90.0), (135.0, 170.0)])
def test_ascent_convention_matches_its_formula(phi, theta) -> None:
    p, t = math.radians(phi), math.radians(theta)
    rz = np.array([[math.cos(p), -math.sin(p), 0], [math.sin(p), math.cos(p), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, math.cos(t), -math.sin(t)], [0, math.sin(t), math.cos(t)]])
    centre, r = np.array([1.0, 2.0, 3.0]), 4.0
    position, up = centre + r * rz @ rx @ np.array([0, 0, 1.0]), rz @ rx @ np.array([0, 1.0, 0])
    c2w = ascent_c2w(phi, theta, tuple(centre), r)
    assert np.allclose(c2w[:3, 3], position, atol=1e-12) and np.allclose(c2w[:3, 1], up, atol=1e-12)
    assert np.allclose(-c2w[:3, 2], (centre - position) / r, atol=1e-12)
    back = c2w[:3, 2]
    phi2, theta2 = ascent_angles(back)
    assert np.allclose(ascent_c2w(phi2, theta2, tuple(centre), r)[:3, 3], position, atol=1e-9)


def _make(tmp_path: Path, scene: str, convention: str, res: int = RES) -> Path:
    out = tmp_path / f"{scene}_{convention}"
    assert main(["make-scene", scene, "--out", str(out), "--res", str(res), "--views", str(VIEWS),
                 "--test-views", str(TEST_VIEWS), "--format", "cinema", "--convention", convention]) == 0
    return out


@pytest.fixture(scope="module")
def databases(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("cinema")
    dbs = {c: _make(root, "tangle_iso", c) for c in ("pycinema", "paraview", "ascent")}
    blender = root / "blender"
    assert main(["make-scene", "tangle_iso", "--out", str(blender), "--res", str(RES), "--views", str(VIEWS),
                 "--test-views", str(TEST_VIEWS), "--quiet"]) == 0
    return {**dbs, "blender": blender}


@pytest.mark.parametrize("convention", ["pycinema", "paraview", "ascent"])
def test_poses_match_the_reference_cameras(databases, convention) -> None:
    spec = get_scene("tangle_iso")
    frames = [f for f in plan_frames(spec, DatasetOptions(RES, VIEWS, TEST_VIEWS)) if f.split == "train"]
    parsed = read_split(databases[convention] / "train.cdb")
    assert parsed.scene.n_frames == len(frames)
    for frame, c2w in zip(frames, parsed.scene.c2w.double().numpy(), strict=True):
        orbit = orbit_c2w(frame.azimuth, frame.elevation, spec.camera_distance)
        if convention == "ascent":  # the camera along the same direction, Ascent's distance and roll
            lo, hi = np.asarray(spec.bbox[0]), np.asarray(spec.bbox[1])
            r = 1.25 * np.linalg.norm(hi - lo)
            expected = ascent_c2w(*ascent_angles(orbit[:3, 2]), tuple(0.5 * (lo + hi)), r)
            assert np.allclose(c2w[:3, 2], orbit[:3, 2], atol=1e-6)
        else:
            expected = orbit
        assert np.abs(c2w - expected).max() < 1e-6
    assert [a.name for a in parsed.scene.param_axes] == ["isovalue"]
    assert parsed.scene.intrinsics.orthographic == (convention == "pycinema")


def test_paraview_database_reads_the_blender_images_and_parameters(databases) -> None:
    cdb, blender = read_split(databases["paraview"] / "train.cdb").scene, load_dataset(databases["blender"])
    assert torch.equal(cdb.images, blender.images)
    assert torch.allclose(cdb.params, blender.params) and cdb.param_axes == blender.param_axes
    assert cdb.intrinsics == blender.intrinsics


def test_pycinema_database_keeps_depth_and_composites_rgba(databases) -> None:
    parsed = read_split(databases["pycinema"] / "train.cdb")
    scene = parsed.scene
    assert scene.depths is not None and scene.depths.shape == scene.images.shape[:3]
    hit = torch.isfinite(scene.depths)
    assert 0 < int(hit.sum()) < hit.numel()
    # where nothing was hit the RGBA's alpha is 0 and the pixel is the white background
    assert int(scene.images[~hit].min()) >= 250
    assert any("detected" in note for note in parsed.notes)


@pytest.mark.parametrize("convention", ["pycinema", "paraview", "ascent"])
def test_conventions_are_detected_without_being_named(databases, convention) -> None:
    sidecar = json.loads((databases[convention] / "train.cdb" / "visnerf_camera.json").read_text())
    assert "convention" not in sidecar
    notes = read_split(databases[convention] / "train.cdb").notes
    assert notes[0].startswith(f"cameras: {convention}, detected")


def test_a_cinema_database_has_one_split(databases) -> None:
    db = databases["paraview"] / "test.cdb"
    assert has_split(db, "train") and not has_split(db, "val")
    spec = get_scene("tangle_iso")
    axes = load_dataset(databases["blender"]).param_axes
    truth = load_ground_truth(db, None, axes)
    assert truth.split == "all rows" and truth.scene.n_frames == TEST_VIEWS and len(spec.axes) == 1
    with pytest.raises(EvaluationError, match="has no splits"):
        load_ground_truth(db, "test", axes)


def _copy_db(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def _rewrite_table(db: Path, edit) -> None:
    rows = list(csv.reader((db / "data.csv").read_text().splitlines()))
    edit(rows)
    with (db / "data.csv").open("w", newline="") as f:
        csv.writer(f, lineterminator="\n").writerows(rows)


def _set(rows: list, row: int, column: str, value: str) -> None:
    rows[row][rows[0].index(column)] = value


REFUSALS = [
    ("paraview", lambda db: _rewrite_table(db, lambda r: _set(r, 2, "isovalue", "high")),
     r"row 2, column 'isovalue': 'high' is not a number"),
    ("paraview", lambda db: _rewrite_table(db, lambda r: _set(r, 3, "isovalue", "NaN")),
     r"row 3, column 'isovalue': the value must be finite"),
    ("paraview", lambda db: _rewrite_table(db, lambda r: _set(r, 1, "theta", "")),
     r"row 1, column 'theta': the value is missing"),
    ("paraview", lambda db: (db / "r_2.png").unlink(), r"row 3, column 'FILE_png': image 'r_2.png' not found"),
    ("paraview", lambda db: (db / "r_1.png").write_bytes(b"not a png"), r"row 2 \(r_1.png\): cannot decode"),
    ("paraview", lambda db: _rewrite_table(db, lambda r: _set(r, 2, "FILE_png", "r_0.png")),
     r"row 2, column 'FILE_png': image 'r_0.png' is also row 1's"),
    ("paraview", lambda db: (db / "visnerf_camera.json").write_text('{"fov_deg": 30}'),
     r"need focal_point and distance"),
    ("paraview", lambda db: (db / "visnerf_camera.json").write_text('{"focal_point": [0, 0, 0], "distance": 2}'),
     r"lens is not known: give fov_deg"),
    ("paraview", lambda db: (db / "visnerf_camera.json").write_text('{"fov": 30}'), r"unknown key\(s\) \['fov'\]"),
    ("paraview", lambda db: _rewrite_table(db, lambda r: [row.pop(r[0].index("theta")) for row in r[::-1]]),
     r"needs angle columns; the table lacks theta"),
    ("ascent", lambda db: (db / "visnerf_camera.json").write_text('{"fov_deg": 30}'), r"Ascent's cameras need the data's bounds"),
    ("ascent", lambda db: (db / "info.json").unlink(), r"does not say how its cameras were placed"),
    ("paraview", lambda db: _rewrite_table(db, lambda r: r[0].__setitem__(r[0].index("producer"), "isovalue")),
     r"repeats the column name"),
]


@pytest.mark.parametrize(("convention", "break_it", "message"), REFUSALS)
def test_bad_databases_are_refused_naming_row_and_column(databases, tmp_path, convention, break_it, message) -> None:
    db = _copy_db(databases[convention] / "train.cdb", tmp_path / "bad.cdb")
    break_it(db)
    with pytest.raises(DatasetError, match=message):
        read_split(db)


def test_images_of_different_sizes_are_refused(databases, tmp_path) -> None:
    from PIL import Image

    db = _copy_db(databases["paraview"] / "train.cdb", tmp_path / "bad.cdb")
    Image.new("RGB", (RES + 2, RES)).save(db / "r_1.png")
    with pytest.raises(DatasetError, match=r"images differ in size: .*row 2 \(r_1.png\) is 18x16"):
        read_split(db)


def test_h5_camera_whose_up_is_parallel_to_its_direction_is_refused(databases, tmp_path) -> None:
    import h5py

    db = _copy_db(databases["pycinema"] / "train.cdb", tmp_path / "bad.cdb")
    with h5py.File(db / "r_2.h5", "r+") as f:
        direction = np.asarray(f["meta/CameraDir"])
        del f["meta/CameraUp"]
        f["meta/CameraUp"] = 2.0 * direction
    with pytest.raises(DatasetError, match=r"row 3 \(r_2.h5\): the up vector .* parallel to the view direction"):
        read_split(db)


def test_h5_images_of_different_lenses_are_refused(databases, tmp_path) -> None:
    import h5py

    db = _copy_db(databases["pycinema"] / "train.cdb", tmp_path / "bad.cdb")
    with h5py.File(db / "r_1.h5", "r+") as f:
        height = float(np.asarray(f["meta/CameraHeight"]).reshape(-1)[0])
        del f["meta/CameraHeight"]
        f["meta/CameraHeight"] = np.asarray([1.5 * height])
    with pytest.raises(DatasetError, match=r"row 2 \(r_1.h5\): its camera .* must share one lens"):
        read_split(db)


def test_options_override_the_sidecar_and_name_the_convention(databases, tmp_path) -> None:
    db = _copy_db(databases["paraview"] / "train.cdb", tmp_path / "opt.cdb")
    (db / "visnerf_camera.json").unlink()
    with pytest.raises(DatasetError, match="need focal_point and distance"):
        read_split(db)
    spec = get_scene("tangle_iso")
    camera = CinemaCamera(focal_point=(0.0, 0.0, 0.0), distance=spec.camera_distance, fov_deg=spec.fov_x_deg)
    reference = read_split(databases["paraview"] / "train.cdb").scene
    assert torch.allclose(read_split(db, cinema=camera).scene.c2w, reference.c2w, atol=1e-6)
    ortho = read_split(db, cinema=CinemaCamera(view_height=1.2)
                       .over(CinemaCamera(focal_point=(0.0, 0.0, 0.0), distance=2.0, fov_deg=30.0))).scene
    assert ortho.intrinsics.orthographic and ortho.intrinsics.view_height == pytest.approx(1.2)


@pytest.mark.slow
def test_train_refuses_a_bad_database_before_writing_anything(databases, tmp_path) -> None:
    db = _copy_db(databases["paraview"] / "train.cdb", tmp_path / "bad.cdb")
    _rewrite_table(db, lambda r: _set(r, 2, "isovalue", "x"))
    out = tmp_path / "m.safetensors"
    run = subprocess.run([sys.executable, "-m", "visnerf.cli", "train", str(db), "--out", str(out)],
                         capture_output=True, text=True)
    assert run.returncode == 2 and "row 2, column 'isovalue'" in run.stderr, run.stderr
    assert list(tmp_path.iterdir()) == [db]


@pytest.mark.slow
def test_cinema_options_reach_the_reader(databases, tmp_path) -> None:
    db = _copy_db(databases["paraview"] / "train.cdb", tmp_path / "opt.cdb")
    (db / "visnerf_camera.json").unlink()
    out = tmp_path / "m.safetensors"
    run = subprocess.run([sys.executable, "-m", "visnerf.cli", "train", str(db), "--out", str(out),
                          "--cinema-fov-deg", "30", "--cinema-distance", "2.1", "--cinema-focal-point", "0,0,0",
                          "--iterations", "2", "--quiet"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert "paraview, detected: the 'producer' column names ParaView" in run.stderr
    info = subprocess.run([sys.executable, "-m", "visnerf.cli", "info", str(out)], capture_output=True, text=True)
    notes = json.loads(info.stdout)["provenance"]["dataset_notes"]  # the training record says how columns were read
    assert any("the 'producer' column names ParaView" in note for note in notes), notes
