"""The settings ``visnerf train`` chooses from the data: each on a scene where it must be made and
one where it must not."""

import dataclasses
from pathlib import Path

import pytest
import torch

from visnerf.config import FieldConfig, TrainConfig
from visnerf.config.recipe import RECIPE
from visnerf.training.recipe import (
    choose_recipe,
    content_box,
    param_rank,
    surface_density,
    voxels_for,
)
from visnerf.training.scene_traits import faint_fraction, frames_cut_by_border, pixel_footprint, views_per_setting

NYX = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "nyx"


def choices_of(recipe) -> dict[str, object]:
    return {c.name: c.value for c in recipe.choices}


@pytest.mark.slow
def test_opaque_surfaces_get_a_surface_density_and_volumes_do_not(surface_scene, volume_scene):
    surface = choose_recipe(surface_scene, TrainConfig(), FieldConfig())
    volume = choose_recipe(volume_scene, TrainConfig(), FieldConfig())
    assert faint_fraction(surface_scene, 2) < 0.01 < faint_fraction(volume_scene, 2)
    assert surface.field.density_scale > 50.0
    assert volume.field == FieldConfig()
    # The fog a fresh field starts from is the same either way (softplus(shift) * scale).
    fog = torch.nn.functional.softplus(torch.tensor(FieldConfig().density_shift)).item()
    got = torch.nn.functional.softplus(torch.tensor(surface.field.density_shift)).item() * surface.field.density_scale
    assert got == pytest.approx(fog, rel=1e-5)
    assert "opaque" in next(c.reason for c in surface.choices if c.name == "density_scale")
    # Only opaque content reads the facing cosines (a headlight's shading); a volume keeps none.
    assert surface.field.facing_vectors == RECIPE.surface.facing_vectors > 0 and volume.field.facing_vectors == 0
    assert "opaque" in next(c.reason for c in surface.choices if c.name == "facing_vectors")
    assert "translucent" in next(c.reason for c in volume.choices if c.name == "facing_vectors")
    # Opaque content gets total variation on its density and appearance; a volume seen by many views a setting none.
    assert views_per_setting(volume_scene) >= RECIPE.sparse_views
    assert surface.train.tv_weight_density == RECIPE.surface.tv_density > volume.train.tv_weight_density == 0.0
    assert surface.train.tv_weight_appearance == RECIPE.surface.tv_appearance > 0.0
    assert volume.train.tv_weight_appearance == TrainConfig().tv_weight_appearance
    for name in ("tv_weight_density", "tv_weight_appearance"):
        assert "opaque" in next(c.reason for c in surface.choices if c.name == name)
        assert "translucent" in next(c.reason for c in volume.choices if c.name == name)
    # Only opaque content colours its light samples at random.
    assert surface.train.colour_weight_floor == RECIPE.surface.colour_floor > volume.train.colour_weight_floor == 0.0
    assert "opaque" in next(c.reason for c in surface.choices if c.name == "colour_weight_floor")
    assert "translucent" in next(c.reason for c in volume.choices if c.name == "colour_weight_floor")
    # Only opaque content samples a carved grid grown past the visual hull.
    assert surface.train.carve_dilation == RECIPE.surface.carve_dilation > volume.train.carve_dilation == 0
    assert "opaque" in next(c.reason for c in surface.choices if c.name == "carve_dilation")
    assert "translucent" in next(c.reason for c in volume.choices if c.name == "carve_dilation")
    # Only opaque content keeps a ring of empty cells around its refined grids.
    assert surface.train.occupancy_refine_dilation == RECIPE.surface.refine_dilation > 0
    assert volume.train.occupancy_refine_dilation == TrainConfig().occupancy_refine_dilation == 0
    # Only opaque surfaces of a level field draw a share of their rays from the images' silhouettes.
    assert surface.train.silhouette_ray_fraction == volume.train.silhouette_ray_fraction == 0.0
    assert "without a level field" in next(c.reason for c in surface.choices if c.name == "silhouette_ray_fraction")
    assert "translucent" in next(c.reason for c in volume.choices if c.name == "silhouette_ray_fraction")
    # Only opaque content drops occluded samples from a training step.
    assert surface.train.stop_eps == TrainConfig().stop_eps > 0 and "stop_eps" not in choices_of(surface)
    assert volume.train.stop_eps == 0.0 and "translucent" in next(c.reason for c in volume.choices
                                                                   if c.name == "stop_eps")


def test_surface_density_scale_is_one_over_the_voxel():
    scale, shift = surface_density(0.01, 0.127)
    assert scale == pytest.approx(100.0)
    assert torch.nn.functional.softplus(torch.tensor(shift, dtype=torch.float64)).item() * scale == pytest.approx(0.127)


def test_framed_content_carves_at_three_quarters_and_cut_content_at_zero(volume_scene):
    framed = choose_recipe(volume_scene, TrainConfig(), FieldConfig())
    assert frames_cut_by_border(volume_scene, 2) == 0
    assert framed.train.carve_min_seen_fraction == RECIPE.carve_framed_fraction
    images = volume_scene.images.clone()
    images[::3, :, 0] = 0  # content reaching the left edge of every third image
    cut_scene = dataclasses.replace(volume_scene, images=images)
    assert frames_cut_by_border(cut_scene, 2) == len(range(0, volume_scene.n_frames, 3))
    cut = choose_recipe(cut_scene, TrainConfig(), FieldConfig())
    assert cut.train.carve_min_seen_fraction == 0.0
    assert "border" in next(c.reason for c in cut.choices if c.name == "carve_min_seen_fraction")


def test_resolution_follows_the_pixel_size(volume_scene):
    recipe = choose_recipe(volume_scene, TrainConfig(), FieldConfig())
    # 32 pixels over 30 degrees at a distance of 2.1: a pixel is 0.0352 world units at the origin.
    assert pixel_footprint(volume_scene, torch.zeros(3)) == pytest.approx(2.1 * 2 * 0.26795 / 32, rel=1e-3)
    box = content_box(volume_scene, recipe.carved)
    assert recipe.train.resolution_final == voxels_for(box[1] - box[0], RECIPE.voxel_per_pixel * 2.1 * 2 * 0.26795 / 32)
    assert recipe.train.resolution_final % 8 == 0
    assert recipe.train.resolution_init <= recipe.train.resolution_final


def test_voxels_for_rounds_to_eight_within_the_range():
    assert voxels_for(torch.tensor([0.388, 0.388, 0.388]), 0.93 * 0.0020934) == 200
    assert voxels_for(torch.tensor([1.0, 1.0, 1.0]), 1.0) == 48
    assert voxels_for(torch.tensor([1.0, 1.0, 1.0]), 1e-4) == 256


def test_parameter_factors_are_left_out_only_without_parameters(surface_scene, volume_scene):
    assert choices_of(choose_recipe(surface_scene, TrainConfig(), FieldConfig())).get("parameter_axes") == 0
    assert "parameter_axes" not in choices_of(choose_recipe(volume_scene, TrainConfig(), FieldConfig()))


def test_settings_the_user_gave_are_kept(surface_scene):
    base = TrainConfig(resolution_final=40, carve_min_seen_fraction=0.1, tv_weight_density=0.0, tv_weight_appearance=0.0,
                       colour_weight_floor=0.0, carve_dilation=0,
                       occupancy_refine_dilation=0, silhouette_ray_fraction=0.0, time_budget_s=60.0)
    field = FieldConfig(density_scale=3.0, facing_vectors=0, sh_degree=2)
    recipe = choose_recipe(surface_scene, base, field,
                           frozenset({"resolution_final", "carve_min_seen_fraction", "density_scale", "facing_vectors",
                                      "tv_weight_density", "tv_weight_appearance", "colour_weight_floor",
                                      "carve_dilation", "occupancy_refine_dilation", "silhouette_ray_fraction",
                                      "rays_per_voxel", "n_param_components", "sh_degree"}))
    assert recipe.train.rays_per_voxel == 0.0
    assert recipe.train.resolution_final == 40 and recipe.train.carve_min_seen_fraction == 0.1
    assert recipe.train.colour_weight_floor == 0.0 and recipe.train.carve_dilation == 0
    assert recipe.train.occupancy_refine_dilation == 0 and recipe.train.silhouette_ray_fraction == 0.0
    assert recipe.train.tv_weight_density == recipe.train.tv_weight_appearance == 0.0
    assert recipe.field.density_scale == 3.0 and recipe.field.facing_vectors == 0 and recipe.field.sh_degree == 2
    assert all(c.reason == "set by the user" for c in recipe.choices if c.name != "parameter_axes")


@pytest.mark.slow
@pytest.mark.skipif(not (NYX / "transforms_train.json").exists(), reason="../shared/data/nyx is not here")
def test_nyx_gets_the_tuned_recipe():
    from visnerf.data.datasets import load_dataset

    recipe = choose_recipe(load_dataset(NYX, "train"), TrainConfig(), FieldConfig())
    assert recipe.train.resolution_final == 200
    assert recipe.train.carve_min_seen_fraction == 0.75
    assert recipe.field == FieldConfig()  # translucent: no surface density
    assert recipe.carved is not None


@pytest.mark.slow
def test_an_isovalue_sweep_gets_a_level_axis_and_other_scenes_do_not(iso_sweep_scene, volume_scene, surface_scene):
    iso = choose_recipe(iso_sweep_scene, TrainConfig(), FieldConfig())
    assert iso.field.level_set_axis == 0
    reason = next(c.reason for c in iso.choices if c.name == "level_set_axis")
    assert "nested along 'isovalue'" in reason and "shrink" in reason
    assert iso.train.tv_weight_density == RECIPE.surface.tv_density > TrainConfig().tv_weight_density
    # Its surfaces, shaded by the level field's normals, draw a share of their rays from the silhouettes.
    assert iso.train.silhouette_ray_fraction == RECIPE.surface.silhouette_rays > 0
    assert "level field" in next(c.reason for c in iso.choices if c.name == "silhouette_ray_fraction")
    # The same opaque images with their isovalues shuffled: the hulls jump in and out, no level axis.
    values = sorted(set(iso_sweep_scene.params[:, 0].tolist()))
    shuffled = dict(zip(values, [values[i] for i in (0, 4, 1, 3, 2)], strict=True))
    params = torch.tensor([[shuffled[v]] for v in iso_sweep_scene.params[:, 0].tolist()])
    mixed = choose_recipe(dataclasses.replace(iso_sweep_scene, params=params), TrainConfig(), FieldConfig())
    assert mixed.field.level_set_axis == -1 and mixed.train.tv_weight_density == RECIPE.surface.tv_density
    assert mixed.train.silhouette_ray_fraction == 0.0
    assert "no axis" in next(c.reason for c in mixed.choices if c.name == "level_set_axis")
    # Translucent content (whose hulls may nest as a transfer function fades it) and K = 0: none.
    for other in (volume_scene, surface_scene):
        recipe = choose_recipe(other, TrainConfig(), FieldConfig())
        assert recipe.field.level_set_axis == -1 and "level_set_axis" not in choices_of(recipe)


def test_a_level_axis_the_user_gave_is_kept(iso_sweep_scene):
    recipe = choose_recipe(iso_sweep_scene, TrainConfig(), FieldConfig(level_set_axis=-1), frozenset({"level_set_axis"}))
    assert recipe.field.level_set_axis == -1
    assert recipe.train.silhouette_ray_fraction == 0.0  # no level field: no silhouette share
    kept = choose_recipe(iso_sweep_scene, TrainConfig(silhouette_ray_fraction=0.6), FieldConfig(),
                         frozenset({"silhouette_ray_fraction"}))
    assert kept.train.silhouette_ray_fraction == 0.6
    assert next(c.reason for c in recipe.choices if c.name == "level_set_axis") == "set by the user"


def test_translucent_content_seen_by_few_views_a_setting_gets_total_variation_and_fewer_view_terms(volume_scene):
    per_setting = int(views_per_setting(volume_scene))
    few = RECIPE.sparse_views - 1
    keep = torch.cat([torch.nonzero((volume_scene.params == p).all(dim=1))[:few, 0]
                      for p in torch.unique(volume_scene.params, dim=0)])
    sparse = volume_scene.subset(keep)
    assert views_per_setting(sparse) == few < per_setting
    recipe = choose_recipe(sparse, TrainConfig(), FieldConfig())
    assert recipe.train.tv_weight_density == recipe.train.tv_weight_appearance == RECIPE.sparse_view_tv > 0.0
    reasons = choices_of_reasons(recipe)
    assert f"seen by {few} views a setting" in reasons["tv_weight_density"] and "density" in reasons["tv_weight_density"]
    assert "appearance" in reasons["tv_weight_appearance"]
    assert recipe.field.sh_degree == RECIPE.sparse_view_sh_degree < FieldConfig().sh_degree
    assert f"seen by {few} views a setting" in reasons["sh_degree"]
    dense = choose_recipe(volume_scene, TrainConfig(), FieldConfig())
    assert dense.train.tv_weight_density == 0.0
    assert dense.field.sh_degree == FieldConfig().sh_degree
    assert f"seen by {per_setting} views a setting" in choices_of_reasons(dense)["tv_weight_density"]


def test_views_per_setting_counts_the_images_of_each_setting(volume_scene, surface_scene):
    assert views_per_setting(surface_scene) == surface_scene.n_frames  # K = 0: one setting
    settings = torch.unique(volume_scene.params, dim=0).shape[0]
    uneven = volume_scene.subset(torch.cat([torch.arange(volume_scene.n_frames), torch.zeros(50, dtype=torch.long)]))
    assert views_per_setting(volume_scene) == volume_scene.n_frames / settings  # evenly spread here
    assert views_per_setting(uneven) == views_per_setting(volume_scene)  # the median, not the mean


@pytest.mark.parametrize(("counts", "components", "rank"), [
    ([3, 3, 5], (16, 48), 4),  # Nyx
    ([5], (16, 48), 4),  # the synthetic scenes: 3 to 5 values an axis
    ([9], (16, 48), 4),
    ([12], (16, 48), 4),
    ([13], (16, 48), 8),
    ([30], (16, 48), 16),  # the lit series
    ([5, 70], (16, 48), 16),  # wants 24: no common divisor that large, the largest
    ([30], (12, 36), 12),  # wants 10: the next divisor of both
    ([2], (2, 6), 2),  # wants 4: the largest divisor of both
])
def test_the_parameter_rank_grows_with_the_longest_axis(counts, components, rank):
    assert param_rank(counts, components) == rank


def test_a_time_budget_bounds_the_grid_by_its_rays_unless_the_grid_is_given(volume_scene):
    budgeted = choose_recipe(volume_scene, TrainConfig(time_budget_s=600.0), FieldConfig())
    assert budgeted.train.rays_per_voxel == RECIPE.rays_per_voxel > 0
    assert "a time budget" in choices_of_reasons(budgeted)["rays_per_voxel"]
    by_steps = choose_recipe(volume_scene, TrainConfig(), FieldConfig())
    assert by_steps.train.rays_per_voxel == 0.0
    assert "no time budget" in choices_of_reasons(by_steps)["rays_per_voxel"]
    given = choose_recipe(volume_scene, TrainConfig(time_budget_s=600.0, resolution_final=96), FieldConfig(),
                          frozenset({"resolution_final"}))
    assert given.train.rays_per_voxel == 0.0 and given.train.resolution_final == 96
    assert "the user's" in choices_of_reasons(given)["rays_per_voxel"]
    assert budgeted.field.n_param_components == 4  # five values on its axis


def choices_of_reasons(recipe) -> dict[str, str]:
    return {c.name: c.reason for c in recipe.choices}


def test_translucent_content_of_one_setting_seen_by_few_views_gets_total_variation_on_appearance_only(volume_scene):
    """K = 0 (one setting): thin translucent shells fog under total variation on the density, which
    the appearance factors keep; the view terms stay few as with parameter axes."""
    import dataclasses

    first = volume_scene.params[0]
    frames = torch.nonzero((volume_scene.params == first).all(dim=1))[: RECIPE.sparse_views - 1, 0]
    one = volume_scene.subset(frames)
    static = dataclasses.replace(one, params=one.params[:, :0], param_axes=())
    assert static.n_params == 0 and views_per_setting(static) < RECIPE.sparse_views
    recipe = choose_recipe(static, TrainConfig(), FieldConfig())
    assert recipe.train.tv_weight_density == 0.0 < recipe.train.tv_weight_appearance == RECIPE.sparse_view_tv
    reasons = choices_of_reasons(recipe)
    assert "one setting" in reasons["tv_weight_density"] and "fog" in reasons["tv_weight_density"]
    assert "one setting" in reasons["tv_weight_appearance"] and "appearance" in reasons["tv_weight_appearance"]
    assert recipe.field.sh_degree == RECIPE.sparse_view_sh_degree
