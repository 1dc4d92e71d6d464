"""``TrainConfig`` refuses sizes and budgets a run cannot use, naming the field."""

import math

import pytest

from visnerf.config import DEFAULT_ITERATIONS, TrainConfig


@pytest.mark.parametrize(("field", "value"), [
    ("iterations", 0),
    ("batch_rays", 0),
    ("batch_rays", -2048),
    ("micro_batch_rays", 0),
    ("micro_batch_samples", 0),
    ("time_budget_s", 0.0),
    ("time_budget_s", -60.0),
    ("time_budget_s", math.nan),
    ("time_budget_s", math.inf),
])
def test_unusable_sizes_and_budgets_are_refused(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        TrainConfig(**{field: value})


def test_the_smallest_usable_values_are_accepted() -> None:
    cfg = TrainConfig(iterations=1, batch_rays=1, micro_batch_rays=1, micro_batch_samples=1, time_budget_s=0.5)
    assert (cfg.batch_rays, cfg.time_budget_s) == (1, 0.5)


def test_a_time_budget_alone_ends_a_run_unless_iterations_are_given() -> None:
    assert TrainConfig().step_limit == DEFAULT_ITERATIONS
    assert TrainConfig(time_budget_s=3600.0).step_limit is None
    assert TrainConfig(iterations=500, time_budget_s=3600.0).step_limit == 500
    assert TrainConfig.from_dict(TrainConfig(time_budget_s=60.0).to_dict()).step_limit is None


def test_a_checkpoint_keeps_the_whole_training_configuration(tmp_path) -> None:
    import dataclasses

    import torch

    from visnerf.checkpoint import read_checkpoint
    from visnerf.testing import make_noise_scene
    from visnerf.training.trainer import Trainer

    cfg = TrainConfig(iterations=1, batch_rays=64, resolution_init=12, resolution_final=12, carve=False,
                      upsample_at=(0.5,), occupancy_refine_at=(0.3, 0.6), lr_factors=0.03, stop_eps=1e-3, seed=7)
    trainer = Trainer(make_noise_scene(), None, cfg, torch.device("cpu"))
    meta, _ = read_checkpoint(trainer.save(tmp_path / "m.safetensors"))
    recorded = meta.provenance.recipe
    assert set(recorded) == {f.name for f in dataclasses.fields(TrainConfig)}
    assert TrainConfig.from_dict(recorded) == cfg


def test_an_older_checkpoints_partial_recipe_reads_with_defaults() -> None:
    assert TrainConfig.from_dict({"batch_rays": 4096, "occupancy_refine_at": [0.25]}) == TrainConfig(
        batch_rays=4096, occupancy_refine_at=(0.25,))
    with pytest.raises(ValueError, match="unknown training configuration keys"):
        TrainConfig.from_dict({"error_sampling_tile": 4})


def test_an_older_checkpoints_colour_threshold_per_sample_is_not_read_as_one_per_voxel() -> None:
    """Version 1 checkpoints stored ``full_weight_threshold``, a weight per sample at whatever
    spacing: read as a weight per voxel it would mean another threshold at every spacing, so the
    migration drops it and the per-voxel default applies; a current document naming it is refused."""
    import pytest

    from visnerf.checkpoint import migrate
    from visnerf.config import RenderConfig
    from visnerf.rendering.render_settings import RenderSettings

    old = {**RenderConfig().to_dict(), "full_weight_threshold": 3e-3, "full_step_ratio": 0.5}
    del old["full_weight_threshold_per_voxel"]
    cfg = RenderConfig.from_dict(migrate({"format_version": 1, "render": old})["render"])
    assert cfg.full_weight_threshold_per_voxel == RenderConfig.full_weight_threshold_per_voxel == 2e-3
    full = RenderSettings.from_config(cfg, (1.0, 1.0, 1.0), "full")
    assert (full.step_ratio, full.weight_threshold_per_voxel) == (0.5, 2e-3)  # 1e-3 a sample at half a voxel
    with pytest.raises(ValueError, match="unknown render configuration keys.*full_weight_threshold"):
        RenderConfig.from_dict(old)


def test_a_version_1_recipe_with_a_retired_setting_still_resumes() -> None:
    """Version 1 runs recorded ``random_background`` (off) in ``provenance.recipe``; the setting is
    gone, so the migration leaves it out and the recipe reads back; a current document naming it
    is refused."""
    import pytest

    from visnerf.checkpoint import migrate

    recipe = {**TrainConfig(batch_rays=1024).to_dict(), "random_background": False}
    migrated = migrate({"format_version": 1, "provenance": {"recipe": recipe, "iterations": 7}})
    assert migrated["provenance"]["iterations"] == 7
    assert TrainConfig.from_dict(migrated["provenance"]["recipe"]).batch_rays == 1024
    assert "random_background" in recipe  # the document given is left as it was
    with pytest.raises(ValueError, match="unknown training configuration keys.*random_background"):
        TrainConfig.from_dict(recipe)
