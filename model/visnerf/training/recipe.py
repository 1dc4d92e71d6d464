"""The training recipe chosen from the data: what ``visnerf train`` uses when no flag says otherwise.

``TrainConfig``'s defaults hold what suits every scene; what depends on the dataset is chosen here
from the images and cameras alone, each choice with the reason ``visnerf info`` shows:

- the final grid: ``RECIPE.voxel_per_pixel`` voxels a pixel at the content, over the carved box,
  and under a time budget no more than the run's rays over ``RECIPE.rays_per_voxel``
  (``training.grid_budget``);
- the parameter factors' rank: 4, or a ``RECIPE.values_per_param_component``-th of the longest
  axis's values where that is more; none for K = 0;
- the carving's ``min_seen_fraction``: ``RECIPE.carve_framed_fraction`` where every image frames
  its content whole, else 0;
- for opaque content (no faint foreground pixel): surface density scaled by one over the voxel,
  occluded samples dropped, light samples coloured at random, facing cosines, total variation,
  and, where the settings' hulls nest along an axis, a level-set axis with rays on its silhouettes;
- for translucent content seen by fewer than ``RECIPE.sparse_views`` images a setting: view terms
  of ``RECIPE.sparse_view_sh_degree`` and total variation, for K = 0 on the appearance factors alone.

The rule and figure behind each choice are under its ``recipe.*`` id in docs/decisions.md
(docs/decisions.md#recipe.sparse_view_tv, say).
"""

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F

from visnerf.config import FieldConfig, RenderConfig, TrainConfig
from visnerf.config.recipe import RECIPE
from visnerf.data.carving import carve_occupancy
from visnerf.data.nesting import describe as describe_nesting
from visnerf.data.nesting import nested_axis
from visnerf.data.scene import SceneData, estimate_bbox
from visnerf.rendering.occupancy import occupied_bounds
from visnerf.training.scene_traits import SceneTraits, scene_traits

if TYPE_CHECKING:
    from visnerf.training.trainer import Trainer

CHOSEN_FIELDS = frozenset({("TrainConfig", "resolution_final"), ("TrainConfig", "carve_min_seen_fraction"),
                           ("FieldConfig", "density_scale"), ("FieldConfig", "density_shift"),
                           ("TrainConfig", "stop_eps"), ("FieldConfig", "facing_vectors"),
                           ("FieldConfig", "level_set_axis"), ("TrainConfig", "tv_weight_density"),
                           ("TrainConfig", "tv_weight_appearance"), ("TrainConfig", "colour_weight_floor"),
                           ("TrainConfig", "carve_dilation"), ("TrainConfig", "occupancy_refine_dilation"),
                           ("TrainConfig", "silhouette_ray_fraction"), ("FieldConfig", "n_param_components"),
                           ("TrainConfig", "rays_per_voxel"), ("FieldConfig", "sh_degree")})
"""The configuration fields ``choose_recipe`` sets from the data unless the user gives them
(``RULES``, and ``density_shift`` with ``density_scale``)."""


def surface_density(voxel: float, fog: float) -> tuple[float, float]:
    """``(density_scale, density_shift)`` for surfaces: a scale of one over the voxel size, and
    the shift that keeps the fresh field's fog at ``fog`` per world unit
    (``softplus(shift) * scale = fog``)."""
    scale = 1.0 / voxel
    return scale, math.log(math.expm1(fog / scale))


def voxels_for(extent: torch.Tensor, voxel: float) -> int:
    """Voxels per axis (cube root of the count) that give cells of size ``voxel`` over a box of
    ``extent``, a multiple of 8 within ``RECIPE.resolution_range``."""
    per_axis = float(torch.prod(extent)) ** (1.0 / 3.0) / voxel
    lo, hi = RECIPE.resolution_range
    return int(min(hi, max(lo, 8 * round(per_axis / 8))))


@dataclass(frozen=True)
class Choice:
    """One setting chosen from the data, and why."""

    name: str
    value: object
    reason: str

    def to_dict(self) -> dict[str, object]:
        return {"name": self.name, "value": self.value, "reason": self.reason}


@dataclass(frozen=True)
class Recipe:
    """The configuration a dataset trains with, and the choices made from it."""

    train: TrainConfig
    field: FieldConfig
    choices: tuple[Choice, ...]
    carved: tuple[torch.Tensor, torch.Tensor] | None
    """The carved grid and the box it covers, for the trainer (None: not carved)."""

    def describe(self) -> list[dict[str, object]]:
        return [c.to_dict() for c in self.choices]


@dataclass
class _Context:
    """What the rules read and write while a recipe is chosen: the data's traits, the values chosen
    so far (``train`` and ``field``), and the carving, made once the carving rule has decided."""

    scene: SceneData
    traits: SceneTraits
    base: TrainConfig
    base_field: FieldConfig
    train: dict[str, object] = dataclasses.field(default_factory=dict)
    field: dict[str, object] = dataclasses.field(default_factory=dict)
    carved: tuple[torch.Tensor, torch.Tensor] | None = None
    box: torch.Tensor | None = None
    fixed: frozenset[str] = frozenset()
    """The settings the user gave."""

    def value(self, name: str) -> object:
        """The value of setting ``name`` now: chosen, else the base configuration's."""
        if name in self.train:
            return self.train[name]
        if name in self.field:
            return self.field[name]
        return getattr(self.base if hasattr(self.base, name) else self.base_field, name)

    def carve(self) -> None:
        base = self.base
        self.carved = carve_content(self.scene, base.carve, base.carve_resolution, base.carve_tolerance,
                                    float(self.value("carve_min_seen_fraction")))  # type: ignore[arg-type]
        self.box = content_box(self.scene, self.carved)

    def final_resolution(self) -> int:
        return int(self.value("resolution_final"))  # type: ignore[call-overload]


Decision = tuple[object, str] | None
"""A rule's answer: (the value chosen, why), or None where it leaves the setting as it is (and
says why through ``keep``)."""


@dataclass(frozen=True)
class _Rule:
    """One setting the data decide: its name, whether it lives in the field's configuration, and
    the function that decides it (returning the value and the reason, or the reason it is kept)."""

    name: str
    decide: Callable[[_Context], tuple[object | None, str] | None]
    in_field: bool = False


def _carve_seen(ctx: _Context) -> tuple[object, str]:
    scene, traits = ctx.scene, ctx.traits
    if traits.framed:
        return RECIPE.carve_framed_fraction, (f"every one of the {scene.n_frames} training images shows its "
                                       "content clear of the border, so content is in every view's frame: cells "
                                       "that a quarter of their setting's views do not frame are carved")
    return 0.0, (f"{traits.border_frames} of {scene.n_frames} training images have content on their border: a "
                 "cell only a few views frame may still be content")


def _resolution(ctx: _Context) -> tuple[object, str]:
    assert ctx.box is not None
    extent = ctx.box[1] - ctx.box[0]
    footprint = ctx.traits.pixel_footprint
    sizes = ", ".join(f"{float(e):.3f}" for e in extent)
    return voxels_for(extent, RECIPE.voxel_per_pixel * footprint), (
        f"a pixel spans {footprint:.5f} world units at the content; voxels of {RECIPE.voxel_per_pixel} pixel over the "
        f"content box ({sizes})")


def _grid_budget(ctx: _Context) -> Decision:
    if ctx.base.time_budget_s is None:
        return None, "no time budget: the final grid is the pixel footprint's"
    if "resolution_final" in ctx.fixed:
        return None, "the final grid is the user's"
    return RECIPE.rays_per_voxel, (
        f"a time budget: at each upsampling the final grid is cut to at most the rays the budget will see (from "
        f"the rays a second measured at the grid before) over {RECIPE.rays_per_voxel:g} voxels, never under the "
        "grid reached")


def param_rank(value_counts: list[int], components: tuple[int, int]) -> int:
    """Parameter components for axes of ``value_counts`` training values: the smallest count that
    divides both VM component counts and is at least ``FieldConfig``'s default and a
    ``RECIPE.values_per_param_component``-th of the longest axis's values (the largest common
    divisor where none is that large)."""
    least = FieldConfig.n_param_components
    want = max(least, math.ceil(max(value_counts) / RECIPE.values_per_param_component))
    common = math.gcd(*components)
    return next((d for d in range(want, common + 1) if common % d == 0), common)


def _param_rank(ctx: _Context) -> Decision:
    counts = [len(a.values) for a in ctx.scene.param_axes]
    if not counts:
        return None
    components = (int(ctx.value("n_density_components")), int(ctx.value("n_appearance_components")))  # type: ignore[call-overload]
    rank = param_rank(counts, components)
    least, per = FieldConfig.n_param_components, RECIPE.values_per_param_component
    return rank, (f"the longest parameter axis has {max(counts)} training values: {rank} components a parameter "
                  f"factor (at least {least}, and one for every {per} values), dividing the VM components "
                  f"({components[0]}, {components[1]})")


def _density(ctx: _Context) -> tuple[object | None, str]:
    traits, base_field = ctx.traits, ctx.base_field
    if not traits.opaque:
        return None, (f"{100 * traits.faint_fraction:.1f} % of the foreground pixels are faint: translucent "
                      "content, densities as the decoder gives them")
    assert ctx.box is not None
    voxel = float(torch.prod(ctx.box[1] - ctx.box[0])) ** (1.0 / 3.0) / ctx.final_resolution()
    fog = F.softplus(torch.tensor(base_field.density_shift)).item() * base_field.density_scale
    scale, shift = surface_density(voxel, fog)
    ctx.field["density_shift"] = shift
    return scale, (f"{100 * traits.faint_fraction:.1f} % of the foreground pixels are faint (under "
                   f"{100 * RECIPE.surface_max_faint:g} %): opaque surfaces, whose density must reach an "
                   "optical depth of about 10 within a voxel or two; scaled by one over the voxel size, the "
                   f"starting fog kept at {fog:.3f} per world unit (density_shift {shift:.3f})")


def _stop_eps(ctx: _Context) -> Decision:
    if ctx.traits.opaque:
        return None  # no choice recorded: the library default stands
    return 0.0, ("translucent content seldom turns a ray opaque: training steps keep every sample instead of "
                 "marching a density pass to drop occluded ones")


def _opaque_only(value: object, opaque_reason: str, translucent_reason: str) -> Callable[[_Context], Decision]:
    """A setting made for opaque surfaces only: ``value`` there, the base value elsewhere."""
    def decide(ctx: _Context) -> Decision:
        return (value, opaque_reason) if ctx.traits.opaque else (None, translucent_reason)

    return decide


def _total_variation(opaque_value: float, opaque_reason: str, what: str,
                     one_setting: bool) -> Callable[[_Context], Decision]:
    """Total variation on the ``what`` factors: ``opaque_value`` for opaque surfaces, and for
    translucent content seen by few views a setting (``RECIPE.sparse_views``), of one setting too
    where ``one_setting``."""
    def decide(ctx: _Context) -> Decision:
        views = ctx.traits.views_per_setting
        if ctx.traits.opaque:
            return opaque_value, opaque_reason
        if views < RECIPE.sparse_views and ctx.traits.n_params == 0 and not one_setting:
            return None, (f"translucent content of one setting seen by {views:g} views: total variation would "
                          "smear its thin shells into fog, and no setting between training values needs it "
                          "(docs/decisions.md#recipe.sparse_view_tv)")
        if views < RECIPE.sparse_views and ctx.traits.n_params == 0:
            return RECIPE.sparse_view_tv, (f"translucent content of one setting seen by {views:g} views: smooth "
                                           f"{what} factors leave the thin shells' rims to the density, which "
                                           "the views pin down (docs/decisions.md#recipe.sparse_view_tv)")
        if views < RECIPE.sparse_views:
            return RECIPE.sparse_view_tv, (f"translucent content seen by {views:g} views a setting (under "
                                           f"{RECIPE.sparse_views}): so few views fit its {what} with speckle "
                                           "between them; total variation keeps it smooth")
        return None, (f"translucent content seen by {views:g} views a setting: its {what} is seen along every ray "
                      "through it")

    return decide


def _view_terms(ctx: _Context) -> Decision:
    """The view direction's spherical harmonics: of degree ``RECIPE.sparse_view_sh_degree`` for
    translucent content seen by few views a setting, the default elsewhere."""
    views = ctx.traits.views_per_setting
    if ctx.traits.opaque:
        return None, "opaque surfaces: the view terms beside the facing cosines"
    if views < RECIPE.sparse_views:
        return RECIPE.sparse_view_sh_degree, (
            f"translucent content seen by {views:g} views a setting (under {RECIPE.sparse_views}): view terms of a "
            "higher degree fit each view's colours and miss the views between them")
    return None, f"translucent content seen by {views:g} views a setting: enough to fit its view dependence"


def _level_axis(ctx: _Context) -> Decision:
    traits, scene, base = ctx.traits, ctx.scene, ctx.base
    if not (traits.opaque and traits.n_params > 0):
        return None
    min_seen = float(ctx.value("carve_min_seen_fraction"))  # type: ignore[arg-type]
    axis, nesting = nested_axis(scene, estimate_bbox(scene), base.carve_resolution, base.carve_tolerance, min_seen,
                                RECIPE.nest_tolerance)
    measured = "; ".join(describe_nesting(n) for n in nesting)
    if axis >= 0:
        return axis, (f"opaque surfaces whose visual hulls are nested along {scene.param_axes[axis].name!r} (an "
                      f"isovalue sweep): its surfaces are level sets of one field ({measured})")
    return axis, (f"opaque surfaces, but no axis's visual hulls are nested within "
                  f"{100 * RECIPE.nest_tolerance:g} % ({measured})")


def _silhouettes(ctx: _Context) -> Decision:
    if ctx.traits.opaque and int(ctx.value("level_set_axis")) >= 0:  # type: ignore[call-overload]
        return RECIPE.surface.silhouette_rays, ("opaque surfaces of one level field: the images' colour changes at a "
                                         "silhouette from the background to a shaded surface within one pixel, and a "
                                         "surface's error lies there; this share of each batch is drawn from those "
                                         "pixels")
    if ctx.traits.opaque:
        return None, ("opaque surfaces without a level field: their shading is learnt from the pixels inside the "
                      "silhouettes, which a share drawn from the silhouettes would take rays from")
    return None, "translucent content: its silhouettes fade, and its error is spread over the content"


RULES: tuple[_Rule, ...] = (
    _Rule("carve_min_seen_fraction", _carve_seen),
    _Rule("resolution_final", _resolution),
    _Rule("rays_per_voxel", _grid_budget),
    _Rule("n_param_components", _param_rank, in_field=True),
    _Rule("density_scale", _density, in_field=True),
    _Rule("stop_eps", _stop_eps),
    _Rule("colour_weight_floor", _opaque_only(
        RECIPE.surface.colour_floor,
        "opaque surfaces start as a faint fog: samples lighter than this are coloured at random (unbiased), not all "
        "of them, until the surfaces form",
        "translucent content: its colour is spread over many light samples along a ray, every one coloured")),
    _Rule("facing_vectors", _opaque_only(
        RECIPE.surface.facing_vectors,
        "opaque surfaces: their shading follows the cosine between the surface and the view (a light at the "
        "camera), which the colour decoder reads from learnt unit vectors",
        "translucent content: its colours are read with spherical harmonics of the view alone"), in_field=True),
    _Rule("sh_degree", _view_terms, in_field=True),
    _Rule("tv_weight_density", _total_variation(
        RECIPE.surface.tv_density,
        "opaque surfaces: the images pin the density only where a surface is seen, and a few views fit it with a "
        "rough surface (and, with a level axis, leave the surfaces between training values free); total "
        "variation keeps it smooth", "density", one_setting=False)),
    _Rule("tv_weight_appearance", _total_variation(
        RECIPE.surface.tv_appearance,
        "opaque surfaces: each surface point is seen by a few views, whose fit total variation on the appearance "
        "factors carries over to its neighbours", "appearance", one_setting=True)),
    _Rule("carve_dilation", _opaque_only(
        RECIPE.surface.carve_dilation,
        "opaque surfaces: a density that fills the carved hull renders the training silhouettes exactly; grown, "
        "the grid's edge cannot stand in for a surface",
        "translucent content: a filled hull does not fit its images")),
    _Rule("occupancy_refine_dilation", _opaque_only(
        RECIPE.surface.refine_dilation,
        "opaque surfaces: refined grids keep a ring of empty cells, so the grid's edge never cuts a surface that grows",
        "translucent content: refined grids hold only the cells with content (fewer samples a step)")),
    _Rule("level_set_axis", _level_axis, in_field=True),
    _Rule("silhouette_ray_fraction", _silhouettes),
)
"""The settings the data decide, in the order they are decided (the carving follows the first,
the density the grid's size); ``CHOSEN_FIELDS`` names them."""


def choose_recipe(scene: SceneData, base: TrainConfig, base_field: FieldConfig,
                  fixed: frozenset[str] = frozenset()) -> Recipe:
    """``base`` and ``base_field`` with the data-dependent settings chosen for ``scene`` by
    ``RULES``, one loop; those named in ``fixed`` (set by the user) are kept as given and recorded
    as such."""
    ctx = _Context(scene, scene_traits(scene, base.carve_tolerance), base, base_field, fixed=fixed)
    choices: list[Choice] = []
    for rule in RULES:
        if rule.name in fixed:
            choices.append(Choice(rule.name, ctx.value(rule.name), "set by the user"))
        elif (decision := rule.decide(ctx)) is not None:
            value, reason = decision
            if value is not None:
                (ctx.field if rule.in_field else ctx.train)[rule.name] = value
            shown = (round(value, 3) if rule.name == "density_scale" and isinstance(value, float)
                     else ctx.value(rule.name))
            choices.append(Choice(rule.name, shown, reason))
        if rule.name == "carve_min_seen_fraction":
            ctx.carve()
    if ctx.final_resolution() < base.resolution_init:
        ctx.train["resolution_init"] = ctx.final_resolution()
    if ctx.traits.n_params == 0:
        choices.append(Choice("parameter_axes", 0, "one setting in the data (K = 0): no parameter factors"))
    return Recipe(dataclasses.replace(base, **ctx.train), dataclasses.replace(base_field, **ctx.field),  # type: ignore[arg-type]
                  tuple(choices), ctx.carved)


def carve_content(scene: SceneData, carve: bool, resolution: int, tolerance: int,
                  min_seen_fraction: float) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The carved grid over the camera box and that box (None without carving)."""
    if not carve:
        return None
    box = estimate_bbox(scene)
    return carve_occupancy(scene, box, (resolution,) * 3, tolerance, min_seen_fraction=min_seen_fraction), box


def content_box(scene: SceneData, carved: tuple[torch.Tensor, torch.Tensor] | None) -> torch.Tensor:
    """The box training starts from: the carved visual hull's bounds, or the camera box."""
    if carved is None:
        return estimate_bbox(scene)
    bounds = occupied_bounds(*carved)
    return carved[1].clone() if bounds is None else bounds


def recipe_trainer(train: SceneData, val: SceneData | None, base: TrainConfig, base_field: FieldConfig,
                   device: torch.device, render: RenderConfig | None = None,
                   fixed: frozenset[str] = frozenset()) -> "Trainer":
    """A trainer for ``train`` with the recipe chosen from it (``choose_recipe``): the time spent
    looking at the data counts as training time, and the choices go into the checkpoint."""
    from visnerf.training.trainer import Trainer

    t0 = time.perf_counter()
    recipe = choose_recipe(train, base, base_field, fixed)
    trainer = Trainer(train, val, recipe.train, device, field_cfg=recipe.field, render_cfg=render,
                      carved=recipe.carved, setup_seconds=time.perf_counter() - t0)
    trainer.recipe_choices = recipe.describe()
    return trainer
