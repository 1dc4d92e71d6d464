"""Choosing the full-quality sample spacing (``evaluation.spacing``) and ``visnerf calibrate``."""

import math
import subprocess
import sys

import pytest
import torch

from visnerf.checkpoint import read_checkpoint
from visnerf.config import RenderConfig
from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.data.datasets import load_dataset
from visnerf.data.scene import SceneData
from visnerf.evaluation import spacing
from visnerf.testing import make_tiny_checkpoint, make_tiny_field

# Frame error per spacing of the stub renderer below: PSNR 40 dB at the exhaustive half voxel,
# 40 - 20 log10(1.01) = 39.914 dB (0.086 dB lost) at 0.75, 26 dB at one voxel, 14 dB beyond.
ERRORS = {0.5: 0.01, 0.75: 0.0101, 1.0: 0.05, 1.25: 0.2, 1.5: 0.2}


def _scene(n: int = 3) -> SceneData:
    field, axes = make_tiny_field([("a", [0.0, 1.0])])
    c2w = torch.stack([torch.from_numpy(orbit_c2w(30.0 * i, 10.0, 2.0)).float() for i in range(n)])
    return SceneData(
        images=torch.full((n, 6, 6, 3), 128, dtype=torch.uint8), c2w=c2w,
        intrinsics=Intrinsics.from_fov(6, 6, math.radians(40.0)), params=torch.zeros(n, 1),
        param_axes=axes, view_ids=torch.arange(n),
    )


@pytest.fixture()
def stub_render(monkeypatch):
    """Frames that are the ground truth (128/255) plus a known error per spacing."""
    calls = []

    def render_image(field, c2w, intrinsics, params, settings, empty_space=None):
        calls.append(settings)
        return torch.full((intrinsics.height, intrinsics.width, 3), 128 / 255 + ERRORS[settings.step_ratio])

    monkeypatch.setattr(spacing, "render_image", render_image)
    return calls


@pytest.mark.parametrize(("tolerance", "agreement", "expected"),
                         [(0.1, 38.0, 0.75), (0.08, 38.0, 0.5), (20.0, 38.0, 0.75), (20.0, 0.0, 1.0)])
def test_the_coarsest_spacing_within_the_tolerance_is_chosen(stub_render, tolerance, agreement, expected) -> None:
    """One voxel is 28 dB from the exhaustive frames (0.05 against 0.01 off), three quarters 80 dB."""
    field, _ = make_tiny_field([("a", [0.0, 1.0])])
    choice = spacing.choose_full_spacing(field, _scene(), RenderConfig(step_ratio=0.5), tolerance_db=tolerance,
                                         min_agreement_db=agreement)
    assert choice.ratio == expected
    assert choice.agreement_db[1.0] == pytest.approx(20 * math.log10(1 / 0.04), abs=1e-2)
    assert choice.exhaustive_psnr == pytest.approx(40.0, abs=1e-3)
    assert choice.candidate_psnr[1.0] == pytest.approx(20 * math.log10(1 / 0.05), abs=1e-3)
    if expected != 1.0:
        assert choice.candidate_psnr[0.75] == pytest.approx(40.0 - 20 * math.log10(1.01), abs=1e-3)
    # The exhaustive reference takes every sample, within the model's grid; the candidates are
    # full-quality frames.
    ref = stub_render[0]
    assert ref.use_occupancy and ref.weight_threshold_per_voxel == 0.0 and not ref.early_termination and not ref.bf16
    assert all(s.use_occupancy and s.early_termination for s in stub_render[3:])
    assert field.training  # left in the mode it was found in


def test_with_none_within_the_tolerance_the_coarsest_near_the_best_measured_is_served(monkeypatch) -> None:
    """No spacing is within 0.1 dB of the exhaustive frames (full quality loses 0.17 to 0.42 dB at
    every spacing here): the coarsest within 0.1 dB of the best full-quality frames is served, 1.25
    voxel (0.04 dB below one voxel's), not the unmeasured fallback; a candidate far from the
    exhaustive frames (1.5) never counts."""
    errors = {"reference": 0.01, 0.5: 0.0105, 0.75: 0.0103, 1.0: 0.0102, 1.25: 0.01025, 1.5: 0.08}

    def render_image(field, c2w, intrinsics, params, settings, empty_space=None):
        key = "reference" if settings.weight_threshold_per_voxel == 0.0 else settings.step_ratio
        return torch.full((intrinsics.height, intrinsics.width, 3), 128 / 255 + errors[key])

    monkeypatch.setattr(spacing, "render_image", render_image)
    field, _ = make_tiny_field([("a", [0.0, 1.0])])
    choice = spacing.choose_full_spacing(field, _scene(), RenderConfig(step_ratio=0.5), tolerance_db=0.1)
    assert set(choice.candidate_psnr) == {1.5, 1.25, 1.0, 0.75, 0.5}
    assert choice.candidate_psnr[0.5] == pytest.approx(40.0 - 20 * math.log10(1.05), abs=1e-3)
    assert choice.candidate_psnr[1.5] > choice.candidate_psnr[0.5] - 20  # measured, and far off
    assert choice.candidate_psnr[1.0] - choice.candidate_psnr[1.25] == pytest.approx(20 * math.log10(1.025 / 1.02), abs=1e-3)
    assert choice.ratio == 1.25
    # With no candidate close to the exhaustive frames, the exhaustive spacing is served.
    choice = spacing.choose_full_spacing(field, _scene(), RenderConfig(step_ratio=0.5), tolerance_db=0.1,
                                         min_agreement_db=80.0)
    assert choice.ratio == 0.5


def test_the_reference_renders_only_within_the_models_grid() -> None:
    """Real frames: with density outside the grid (cells training stopped fitting), the reference
    is the grid's frame, not the one that also shows that density."""
    from dataclasses import replace

    import numpy as np

    from visnerf.evaluation.metrics import psnr
    from visnerf.rendering.render_settings import RenderSettings
    from visnerf.rendering.renderer import render_image

    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=2, resolution=12)  # density fills the box
    c = (torch.arange(8) + 0.5) / 8 - 0.5
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    field.set_occupancy((x**2 + y**2 + z**2).sqrt() < 0.25)
    scene, cfg = _scene(2), RenderConfig(step_ratio=0.5)
    exhaustive = RenderSettings.from_config(cfg, scene.background, "exhaustive")
    truth = [scene.images[i].numpy().astype(np.float32) / 255.0 for i in range(2)]
    params = scene.normalized_params()

    def mean_psnr(settings: RenderSettings) -> float:
        with torch.inference_mode():
            frames = [render_image(field, scene.c2w[i], scene.intrinsics, params[i], settings).clamp(0, 1).numpy()
                      for i in range(2)]
        return float(np.mean([psnr(f, t) for f, t in zip(frames, truth, strict=True)]))

    within, everywhere = mean_psnr(exhaustive), mean_psnr(replace(exhaustive, use_occupancy=False))
    assert abs(within - everywhere) > 0.5  # the density outside the grid shows
    choice = spacing.choose_full_spacing(field, scene, cfg, tolerance_db=0.1)
    assert choice.exhaustive_psnr == pytest.approx(within, abs=1e-4)


def test_a_model_trained_one_voxel_apart_is_judged_against_half_a_voxel(stub_render) -> None:
    field, _ = make_tiny_field([("a", [0.0, 1.0])])
    choice = spacing.choose_full_spacing(field, _scene(), RenderConfig(step_ratio=1.0), tolerance_db=0.1)
    assert stub_render[0].step_ratio == 0.5
    assert choice.ratio == 0.75 and choice.exhaustive_psnr == pytest.approx(40.0, abs=1e-3)


def test_spacing_rejects_what_it_cannot_measure(stub_render) -> None:
    field, _ = make_tiny_field([("a", [0.0, 1.0])])
    with pytest.raises(ValueError, match="tolerance_db"):
        spacing.choose_full_spacing(field, _scene(), RenderConfig(), tolerance_db=float("nan"))
    with pytest.raises(ValueError, match="max_frames"):
        spacing.choose_full_spacing(field, _scene(), RenderConfig(), max_frames=0)


@pytest.fixture(scope="module")
def plume(tmp_path_factory):
    data = tmp_path_factory.mktemp("calib") / "plume"
    subprocess.run([sys.executable, "-m", "visnerf.cli", "make-scene", "plume_time", "--out", str(data),
                    "--res", "24", "--test-views", "2", "--quiet"], check=True)
    return data


def _calibrate(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "visnerf.cli", "calibrate", *args], capture_output=True, text=True)


@pytest.mark.slow
def test_calibrate_writes_the_spacing_and_nothing_else(plume, tmp_path) -> None:
    axes = load_dataset(plume).param_axes
    ckpt = make_tiny_checkpoint(tmp_path / "tiny.safetensors", [(a.name, list(a.values)) for a in axes])
    before_meta, before = read_checkpoint(ckpt)
    dry = _calibrate(str(ckpt), str(plume), "--holdout-views", "1,3", "--frames", "2", "--dry-run")
    assert dry.returncode == 0, dry.stderr
    assert "full-quality spacing" in dry.stdout and "wrote" not in dry.stdout
    run = _calibrate(str(ckpt), str(plume), "--holdout-views", "1,3", "--frames", "2", "--device", "cpu")
    assert run.returncode == 0, run.stderr
    meta, after = read_checkpoint(ckpt)
    chosen = float(run.stdout.split("wrote full_step_ratio ")[1].split()[0])
    assert meta.render.full_step_ratio == chosen and chosen in (*spacing.CANDIDATES, 0.5)
    assert meta.provenance.full_spacing is not None
    assert meta.render == RenderConfig(**{**before_meta.render.__dict__, "full_step_ratio": chosen})
    assert after.keys() == before.keys() and all(torch.equal(after[k], before[k]) for k in before)


@pytest.mark.slow
def test_calibrate_without_held_out_frames_chooses_on_the_training_frames(plume, tmp_path) -> None:
    """No transforms_val.json and no --holdout-*: the training frames serve, as in training, and the
    checkpoint's note says so."""
    axes = load_dataset(plume).param_axes
    ckpt = make_tiny_checkpoint(tmp_path / "tiny.safetensors", [(a.name, list(a.values)) for a in axes])
    assert not (plume / "transforms_val.json").exists()
    run = _calibrate(str(ckpt), str(plume), "--frames", "2", "--device", "cpu")
    assert run.returncode == 0, run.stderr
    meta, _ = read_checkpoint(ckpt)
    chosen = float(run.stdout.split("wrote full_step_ratio ")[1].split()[0])
    assert meta.render.full_step_ratio == chosen
    assert meta.provenance.full_spacing.endswith(", training frames (none held out)")
    assert meta.provenance.full_spacing in run.stdout


@pytest.mark.slow
@pytest.mark.parametrize(("extra", "message"), [
    (("--holdout-views", "999"), "matches no frame"),
    (("--holdout-views", "1", "--tolerance", "-1"), "tolerance_db"),
])
def test_calibrate_errors_change_nothing(plume, tmp_path, extra, message) -> None:
    axes = load_dataset(plume).param_axes
    ckpt = make_tiny_checkpoint(tmp_path / "tiny.safetensors", [(a.name, list(a.values)) for a in axes])
    blob = ckpt.read_bytes()
    run = _calibrate(str(ckpt), str(plume), *extra)
    assert run.returncode == 2 and message in run.stderr, run.stderr
    assert ckpt.read_bytes() == blob


@pytest.mark.slow
def test_calibrate_names_a_folder_without_frames_and_changes_nothing(plume, tmp_path) -> None:
    axes = load_dataset(plume).param_axes
    ckpt = make_tiny_checkpoint(tmp_path / "tiny.safetensors", [(a.name, list(a.values)) for a in axes])
    blob = ckpt.read_bytes()
    (tmp_path / "empty").mkdir()
    run = _calibrate(str(ckpt), str(tmp_path / "empty"))
    assert run.returncode == 2 and "transforms_train.json" in run.stderr, run.stderr
    assert ckpt.read_bytes() == blob


@pytest.mark.slow
def test_calibrate_rejects_frames_of_other_parameters(plume, tmp_path) -> None:
    ckpt = make_tiny_checkpoint(tmp_path / "tiny.safetensors", [("isovalue", [0.0, 1.0])])
    blob = ckpt.read_bytes()
    run = _calibrate(str(ckpt), str(plume), "--holdout-views", "1")
    assert run.returncode == 2 and "not the checkpoint's" in run.stderr, run.stderr
    assert ckpt.read_bytes() == blob
