"""The recipe's constants (``training.recipe``): how the data's traits turn into settings. The
rule and figure behind each are under its ``recipe.*`` id in docs/decisions.md, e.g.
docs/decisions.md#recipe.voxel_per_pixel."""

from dataclasses import dataclass, field


@dataclass(frozen=True)
class SurfaceRecipe:
    """What opaque scenes get in place of the ``TrainConfig`` and ``FieldConfig`` defaults."""

    facing_vectors: int = 4
    """``FieldConfig.facing_vectors``: a headlight's shading follows the cosine between normal and
    view, too sharp for spherical harmonics of degree 3."""
    tv_density: float = 0.1
    """``TrainConfig.tv_weight_density``: the images pin a surface's density only where it is seen,
    and a level axis's surfaces between training values are its level sets there; total variation
    keeps them smooth."""
    tv_appearance: float = 0.1
    """``TrainConfig.tv_weight_appearance``: a surface point seen by a few views takes its
    neighbours' fits."""
    colour_floor: float = 0.1
    """``TrainConfig.colour_weight_floor``: lighter samples are coloured at random
    (``rendering.colour_sampling``), so the early fog of light samples does not make the first
    steps several times as long as the last."""
    carve_dilation: int = 2
    """``TrainConfig.carve_dilation``: a density filling the exact visual hull renders the training
    silhouettes with the colours painted on; grown by two cells the grid's edge cannot stand in for
    the surface. Translucent content does not fit its images as a filled hull."""
    silhouette_rays: float = 0.25
    """``TrainConfig.silhouette_ray_fraction`` with a level axis: a quarter of each batch's rays from
    the silhouette band (``training.ray_batches.silhouette_pixels``), where an isosurface
    rendering's error lies; only with a level axis, whose normals shade the surface."""
    refine_dilation: int = 1
    """``TrainConfig.occupancy_refine_dilation``: refined grids keep a ring of one empty cell around
    the content, and a surface that grows into the ring gets a new one; a surface pressed against
    the grid's edge would be cut there and its level could run past the images' surface unseen."""


@dataclass(frozen=True)
class RecipeConfig:
    """How the recipe reads a dataset and sizes its grid."""

    voxel_per_pixel: float = 0.93
    """Final voxel size over the pixel footprint at the content: detail at the pixel scale needs
    voxels a little under a pixel."""
    resolution_range: tuple[int, int] = (48, 256)
    """Fewest and most voxels per axis the recipe picks (memory and checkpoint size bound the top)."""
    carve_framed_fraction: float = 0.75
    """``TrainConfig.carve_min_seen_fraction`` where every image frames its content whole."""
    nest_tolerance: float = 0.02
    """Largest share of one setting's visual hull outside its neighbour's for an axis to count as
    nested (``data.nesting``): an isovalue sweep's hulls nest exactly, a timestep series' do not."""
    faint_contrast: float = 0.25
    """A foreground pixel is faint when its difference from the background is below this fraction
    of the 99th percentile of the foreground's differences."""
    surface_max_faint: float = 0.01
    """Most faint foreground pixels (a fraction) for a scene to count as opaque surfaces: isosurface
    renderings have none, volume renderings several per cent."""
    border_pixels: int = 1
    """Width of the image border in which a foreground pixel means content cut by the frame."""
    sparse_views: int = 30
    """A translucent scene with fewer training images a setting than this gets total variation on
    its factors (``sparse_view_tv``): a 20-view series gained by it, Nyx's 42 views did not."""
    sparse_view_tv: float = 0.1
    """``TrainConfig.tv_weight_density`` and ``tv_weight_appearance`` for such a scene with parameter
    axes: few views fit its density and colours with speckle between them, which the images do not
    pin down. A scene of one setting gets it on the appearance factors alone: on the density it
    smears nested thin shells into fog (docs/decisions.md#recipe.sparse_view_tv)."""
    sparse_view_sh_degree: int = 1
    """``FieldConfig.sh_degree`` for such a scene: the 16 view terms of degree 3 fit each of its few
    views' colours and miss the views between them; a 20-view series gained at degree 2 and more
    at 1 (docs/decisions.md#recipe.sparse_view_sh_degree)."""
    values_per_param_component: int = 3
    """Training values of the longest parameter axis per parameter component: rank 4 serves axes of
    up to 12 values, and a 30-timestep series gains from rank 8 over 4 and from 16 over 8."""
    rays_per_voxel: float = 4.0
    """``TrainConfig.rays_per_voxel`` under a time budget: the final grid holds at most the rays the
    budget will see over this many voxels (Nyx's 200 voxels beat 170 at about 5 rays a voxel, a
    512x512 lit series' 146 voxels beat 234 at 0.9)."""
    surface: SurfaceRecipe = field(default_factory=SurfaceRecipe)
    """The settings of opaque scenes."""


RECIPE = RecipeConfig()
"""The recipe ``visnerf train`` uses."""
