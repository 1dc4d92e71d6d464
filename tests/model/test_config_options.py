"""Every configuration field is reachable from `visnerf train`, and what is given lands in the checkpoint."""

import argparse
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from visnerf.checkpoint import read_checkpoint
from visnerf.cli import build_parser
from visnerf.config import FieldConfig, FramesConfig, RenderConfig, TrainConfig
from visnerf.config.recipe import RECIPE
from visnerf.config_options import CONFIG_CLASSES, NOT_OPTIONS, field_docs, option_of


def train_parser() -> argparse.ArgumentParser:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["train"]


def test_every_field_is_an_option_or_left_out_with_a_reason() -> None:
    options = {s for action in train_parser()._actions for s in action.option_strings}
    for cls in CONFIG_CLASSES:
        for f in dataclasses.fields(cls):
            option = option_of(cls, f.name)
            if option is None:
                assert NOT_OPTIONS[(cls.__name__, f.name)]
            else:
                assert option in options, f"{cls.__name__}.{f.name} has no option ({option})"


def test_generated_help_is_the_fields_docstring() -> None:
    text = train_parser().format_help()
    assert field_docs(FieldConfig)["hidden_width"].startswith("Hidden layer width of both decoders. 64 rather")
    assert "Hidden layer width of both decoders (default: 64)" in " ".join(text.split())
    assert "(default: chosen from the data" in text
    assert "--stop-eps" in text and "--no-mixed-precision" in text


@pytest.fixture(scope="module")
def tangle(synthetic_scene):
    return synthetic_scene("tangle_static", 16)


def train(data, out, *options):
    return subprocess.run([sys.executable, "-m", "visnerf.cli", "train", str(data), "--out", str(out),
                           "--iterations", "3", "--quiet", *options], capture_output=True, text=True)


@pytest.mark.slow
def test_given_options_round_trip_through_the_checkpoint(tangle, tmp_path) -> None:
    out = tmp_path / "m.safetensors"
    run = train(tangle, out, "--hidden-width", "32", "--sh-degree", "1", "--density-scale", "40",
                "--l1-weight-rest", "2e-5", "--no-mixed-precision", "--upsample-at", "0.1,0.2", "--betas", "0.8,0.95",
                "--max-samples", "512", "--full-weight-threshold-per-voxel", "0.001", "--stop-eps", "1e-3")
    assert run.returncode == 0, run.stderr
    meta, _ = read_checkpoint(out)
    assert (meta.field.hidden_width, meta.field.sh_degree, meta.field.density_scale) == (32, 1, 40.0)
    assert (meta.render.max_samples, meta.render.full_weight_threshold_per_voxel) == (512, 0.001)
    recipe = TrainConfig.from_dict(meta.provenance.recipe)
    assert recipe.l1_weight_rest == 2e-5 and recipe.mixed_precision is False and recipe.stop_eps == 1e-3
    assert recipe.upsample_at == (0.1, 0.2) and recipe.betas == (0.8, 0.95)
    chosen = {c.name: c.reason for c in meta.provenance.choices}
    assert chosen["density_scale"] == "set by the user"  # the recipe keeps a given density scale
    assert meta.field.facing_vectors > 0 and "opaque" in chosen["facing_vectors"]  # and chooses the rest
    # Whole configurations: every field of each, as given or as the recipe and the run set them.
    assert meta.render == dataclasses.replace(RenderConfig(max_samples=512, full_weight_threshold_per_voxel=0.001),
                                              full_step_ratio=meta.render.full_step_ratio)
    expected_field = FieldConfig(hidden_width=32, sh_degree=1, density_scale=40.0, param_lengths=(),
                                 resolution=meta.field.resolution, facing_vectors=meta.field.facing_vectors)
    assert meta.field == expected_field
    assert recipe == TrainConfig(iterations=3, l1_weight_rest=2e-5, mixed_precision=False, upsample_at=(0.1, 0.2),
                                 betas=(0.8, 0.95), stop_eps=1e-3, resolution_final=recipe.resolution_final,
                                 resolution_init=recipe.resolution_init,
                                 carve_min_seen_fraction=recipe.carve_min_seen_fraction,
                                 tv_weight_density=RECIPE.surface.tv_density, tv_weight_appearance=RECIPE.surface.tv_appearance,
                                 colour_weight_floor=RECIPE.surface.colour_floor, carve_dilation=RECIPE.surface.carve_dilation,
                                 occupancy_refine_dilation=RECIPE.surface.refine_dilation)


@pytest.mark.slow
def test_options_not_given_keep_the_recipe(tangle, tmp_path) -> None:
    out = tmp_path / "d.safetensors"
    assert train(tangle, out).returncode == 0
    meta, _ = read_checkpoint(out)
    recipe = TrainConfig.from_dict(meta.provenance.recipe)
    assert recipe.stop_eps == TrainConfig.stop_eps and recipe.betas == TrainConfig.betas
    assert meta.field.hidden_width == FieldConfig.hidden_width and meta.render.max_samples == RenderConfig.max_samples
    assert meta.field.density_scale > 1.0  # tangle_static is opaque: the recipe's surface density
    assert (recipe.tv_weight_density, recipe.tv_weight_appearance) == (RECIPE.surface.tv_density, RECIPE.surface.tv_appearance)
    assert recipe.colour_weight_floor == RECIPE.surface.colour_floor
    assert (recipe.carve_dilation, recipe.occupancy_refine_dilation) == (RECIPE.surface.carve_dilation, RECIPE.surface.refine_dilation)
    assert recipe.silhouette_ray_fraction == 0.0  # tangle_static has no level field


@pytest.mark.slow
@pytest.mark.parametrize(("options", "message"), [
    (["--hidden-width", "wide"], "expected a whole number"),
    (["--init-scale", "nan"], "expected a finite number"),
    (["--betas", "0.9"], "expected 2 comma-separated values"),
    (["--density-grad-floor", "1.5"], "density_grad_floor must be in [0, 1)"),
    (["--sh-degree", "5"], "sh_degree must be 0..3"),
])
def test_bad_generated_options_are_refused_naming_the_field(tangle, tmp_path, options, message) -> None:
    out = tmp_path / "bad.safetensors"
    run = train(tangle, out, *options)
    assert run.returncode == 2 and message in run.stderr, run.stderr
    assert not out.exists()


@pytest.mark.slow
def test_a_resumed_run_refuses_to_change_its_field(tangle, tmp_path) -> None:
    first = tmp_path / "a.safetensors"
    assert train(tangle, first).returncode == 0
    run = train(tangle, tmp_path / "b.safetensors", "--resume", str(first), "--hidden-width", "16")
    assert run.returncode == 2 and "--hidden-width would change the field" in run.stderr
    info = json.loads(subprocess.run([sys.executable, "-m", "visnerf.cli", "info", str(first)],
                                     capture_output=True, text=True, check=True).stdout)
    assert info["provenance"]["recipe"]["batch_rays"] == TrainConfig.batch_rays


def command_parser(name: str) -> argparse.ArgumentParser:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


@pytest.mark.parametrize("command", ["render", "animate"])
def test_every_frames_field_is_an_option_of_render_and_animate(command: str) -> None:
    options = {s for action in command_parser(command)._actions for s in action.option_strings}
    for f in dataclasses.fields(FramesConfig):
        assert option_of(FramesConfig, f.name) in options, f.name


@pytest.mark.slow
def test_render_takes_its_chunks_from_the_options_and_refuses_bad_ones(tmp_path) -> None:
    """Chunks and segments change how a frame is cut into work, not the frame (a ray's samples
    are the same whatever its segments; early termination is judged at segment ends, so a level
    of 8 bits apart at most); a value FramesConfig refuses is an error naming the field."""
    from PIL import Image

    checkpoint = sorted((Path(__file__).parents[2] / "checkpoints").glob("*.safetensors"))[0]

    def render(out, *options):
        return subprocess.run([sys.executable, "-m", "visnerf.cli", "render", str(checkpoint), "--size", "48x40",
                               "-o", str(out), *options], capture_output=True, text=True)

    plain, cut = tmp_path / "plain.png", tmp_path / "cut.png"
    assert render(plain).returncode == 0
    run = render(cut, "--chunk-rays", "100", "--segment-samples", "32", "--first-segment-samples", "4")
    assert run.returncode == 0, run.stderr
    a, b = (np.asarray(Image.open(p), dtype=int) for p in (plain, cut))
    assert a.shape == b.shape == (40, 48, 3) and int(abs(a - b).max()) <= 1
    bad = render(tmp_path / "bad.png", "--segment-samples", "32", "--first-segment-samples", "64")
    assert bad.returncode == 2 and "first_segment_samples (64) must not exceed segment_samples (32)" in bad.stderr
    assert not (tmp_path / "bad.png").exists()
