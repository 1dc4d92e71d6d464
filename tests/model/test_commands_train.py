"""``visnerf train``: the sample spacing and carving options, and what ``--resume`` keeps."""

import subprocess
import sys

import pytest
import torch

from visnerf.checkpoint import read_checkpoint
from visnerf.config import TrainConfig
from visnerf.config.recipe import RECIPE


def _visnerf(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "visnerf.cli", *args], capture_output=True, text=True)


@pytest.fixture(scope="module")
def plume(tmp_path_factory):
    data = tmp_path_factory.mktemp("train_cli") / "plume"
    made = _visnerf("make-scene", "plume_time", "--out", str(data), "--res", "16", "--views", "12",
                    "--test-views", "2", "--quiet")
    assert made.returncode == 0, made.stderr
    return data


@pytest.mark.slow
def test_step_ratio_is_stored_and_kept_on_resume(plume, tmp_path) -> None:
    first = tmp_path / "m.safetensors"
    run = _visnerf("train", str(plume), "--out", str(first), "--iterations", "6", "--resolution", "16",
                   "--step-ratio", "1.25", "--carve-min-seen-fraction", "0.5", "--occupancy-refine-at", "0.5,0.9", "--occupancy-refine-dilation", "0", "--device", "cpu", "--quiet")
    assert run.returncode == 0, run.stderr
    meta, _ = read_checkpoint(first)
    assert meta.render.step_ratio == 1.25 and meta.provenance.iterations == 6
    resumed = tmp_path / "r.safetensors"
    run = _visnerf("train", str(plume), "--out", str(resumed), "--iterations", "9", "--resume", str(first),
                   "--device", "cpu", "--quiet")
    assert run.returncode == 0, run.stderr
    meta, _ = read_checkpoint(resumed)
    assert meta.render.step_ratio == 1.25 and meta.provenance.iterations == 9


@pytest.mark.slow
def test_factor_storage_and_sampled_density_gradients(plume, tmp_path) -> None:
    first = tmp_path / "q.safetensors"
    run = _visnerf("train", str(plume), "--out", str(first), "--iterations", "5", "--resolution", "16",
                   "--factor-storage", "int8", "--density-grad-keep", "0.25", "--tv-appearance", "0",
                   "--lr-factors", "0.03", "--lr-decay-ratio", "0.05", "--lr-networks", "0.002",
                   "--weight-average-span", "0.2", "--weight-average-from", "0.4",
                   "--micro-batch-rays", "64", "--micro-batch-samples", "4096", "--device", "cpu", "--quiet")
    assert run.returncode == 0, run.stderr
    meta, tensors = read_checkpoint(first)
    assert meta.field.factor_storage == "int8" and tensors["density_grid.planes.0"].dtype == torch.int8
    recipe = meta.provenance.recipe
    assert recipe["tv_weight_appearance"] == 0.0 and recipe["density_grad_keep"] == 0.25
    # 12 views a setting: the recipe's total variation for sparse views, on appearance overruled by the flag
    assert recipe["tv_weight_density"] == RECIPE.sparse_view_tv and recipe["batch_rays"] == TrainConfig.batch_rays
    assert recipe["lr_factors"] == 0.03 and recipe["lr_decay_ratio"] == 0.05
    assert recipe["lr_networks"] == 0.002
    assert recipe["weight_average_span"] == 0.2 and recipe["weight_average_from"] == 0.4
    resumed = tmp_path / "h.safetensors"
    run = _visnerf("train", str(plume), "--out", str(resumed), "--iterations", "7", "--resume", str(first),
                   "--factor-storage", "float16", "--device", "cpu", "--quiet")
    assert run.returncode == 0, run.stderr
    meta, tensors = read_checkpoint(resumed)
    assert meta.field.factor_storage == "float16" and tensors["density_grid.planes.0"].dtype == torch.float16


@pytest.mark.slow
@pytest.mark.parametrize(("option", "value", "message"), [
    ("--step-ratio", "0", "step_ratio must be a finite number above 0"),
    ("--step-ratio", "nan", "expected a finite number"),
    ("--carve-min-seen-fraction", "1.5", "carve_min_seen_fraction must be in [0, 1]"),
    ("--occupancy-refine-at", "0.5,0.2", "occupancy_refine_at must increase"),
    ("--occupancy-refine-at", "0.5,2", "occupancy_refine_at must hold fractions in [0, 1]"),
    ("--density-grad-keep", "0", "density_grad_keep must be in (0, 1]"),
    ("--tv-appearance", "-0.1", "tv_weight_appearance must be a finite number of at least 0"),
    ("--lr-factors", "0", "lr_factors must be a finite number above 0"),
    ("--lr-factors", "inf", "expected a finite number"),
    ("--lr-networks", "-0.001", "lr_networks must be a finite number above 0"),
    ("--lr-decay-ratio", "0", "lr_decay_ratio must be in (0, 1]"),
    ("--lr-decay-ratio", "1.5", "lr_decay_ratio must be in (0, 1]"),
    ("--occupancy-refine-dilation", "-1", "occupancy_refine_dilation must be >= 0"),
    ("--resolution", "0", "resolution_final must be a whole number of at least 2"),
    ("--occupancy-refine-dilation", "0.5", "expected a whole number"),
    ("--factor-storage", "int4", "expected one of float32, float16, int8"),
    ("--batch-rays", "0", "batch_rays must be at least 1"),
    ("--micro-batch-rays", "0", "micro_batch_rays must be at least 1"),
    ("--micro-batch-samples", "-5", "micro_batch_samples must be at least 1"),
    ("--weight-average-span", "-0.1", "weight_average_span must be a progress fraction >= 0"),
    ("--weight-average-from", "1.5", "weight_average_from must be in [0, 1]"),
    ("--batch-rays", "2048.5", "expected a whole number"),
    ("--iterations", "-1", "iterations must be at least 1"),
    ("--time-budget", "0", "above 0"),
    ("--validate-every", "-5", "validate_every_s must be a finite number above 0"),
    ("--validate-every", "nan", "expected a finite number"),
    ("--max-samples", "0", "max_samples must be a whole number of at least 1"),
    ("--hidden-width", "0", "hidden_width must be a whole number of at least 1"),
])
def test_bad_training_options_are_refused(plume, tmp_path, option, value, message) -> None:
    out = tmp_path / "m.safetensors"
    run = _visnerf("train", str(plume), "--out", str(out), option, value, "--quiet")
    assert run.returncode == 2 and message in run.stderr, run.stderr
    assert not out.exists()


@pytest.mark.slow
def test_an_isovalue_sweep_trains_with_a_level_axis_unless_the_user_says(tmp_path) -> None:
    data = tmp_path / "iso"
    made = _visnerf("make-scene", "tangle_iso", "--out", str(data), "--res", "16", "--views", "12",
                    "--test-views", "2", "--quiet")
    assert made.returncode == 0, made.stderr
    chosen = tmp_path / "chosen.safetensors"
    run = _visnerf("train", str(data), "--out", str(chosen), "--iterations", "3", "--device", "cpu", "--quiet")
    assert run.returncode == 0, run.stderr
    meta, tensors = read_checkpoint(chosen)
    assert meta.field.level_set_axis == 0 and meta.field.facing_vectors > 0 and "levels.table" in tensors
    reasons = {c.name: c.reason for c in meta.provenance.choices}
    assert "nested along 'isovalue'" in reasons["level_set_axis"]
    # Field options given on the command line are kept, not chosen again (the facing vectors were
    # overridden by the recipe before).
    given = tmp_path / "given.safetensors"
    run = _visnerf("train", str(data), "--out", str(given), "--iterations", "3", "--level-set-axis", "-1",
                   "--facing-vectors", "0", "--device", "cpu", "--quiet")
    assert run.returncode == 0, run.stderr
    meta, tensors = read_checkpoint(given)
    assert meta.field.level_set_axis == -1 and meta.field.facing_vectors == 0 and "levels.table" not in tensors
    reasons = {c.name: c.reason for c in meta.provenance.choices}
    assert reasons["level_set_axis"] == reasons["facing_vectors"] == "set by the user"
