"""Space carving against analytic silhouettes of spheres: no content cell is ever carved, far
empty space is, and the grid is the union over parameter settings."""

import math

import numpy as np
import pytest
import torch

from visnerf.checkpoint import ParamAxis
from visnerf.data.cameras import Intrinsics, image_rays, orbit_c2w
from visnerf.data.carving import carve_occupancy, cell_centres_flat, foreground_masks, setting_groups
from visnerf.data.scene import SceneData
from visnerf.scenes.protocol import direction_to_angles, icosphere_vertices

RES = 24
BOX = torch.tensor([[-0.6, -0.6, -0.6], [0.6, 0.6, 0.6]])


def sphere_images(c2ws: torch.Tensor, intr: Intrinsics, centre: tuple[float, float, float], radius: float) -> torch.Tensor:
    """Black sphere silhouettes on white: uint8 [n, h, w, 3], exact ray/sphere test per pixel."""
    out = []
    c = torch.tensor(centre, dtype=torch.float64)
    for c2w in c2ws:
        o, d = image_rays(c2w.double(), intr)  # [h, w, 3]
        oc = o - c
        b = (oc * d).sum(-1)
        disc = b * b - ((oc * oc).sum(-1) - radius**2)
        hit = (disc >= 0) & (-b + disc.clamp_min(0).sqrt() > 0)
        img = torch.full((*hit.shape, 3), 255, dtype=torch.uint8)
        img[hit] = 0
        out.append(img)
    return torch.stack(out)


def make_scene(spheres: list[tuple[tuple[float, float, float], float]], size: int = 48) -> SceneData:
    """One parameter setting per sphere, 42 icosphere views each, cameras at distance 2.1."""
    intr = Intrinsics.from_fov(size, size, math.radians(40.0))
    dirs = icosphere_vertices(1)
    poses = torch.tensor(np.stack([orbit_c2w(*direction_to_angles(d), 2.1) for d in dirs]), dtype=torch.float32)
    images, c2w, params, views = [], [], [], []
    for k, (centre, radius) in enumerate(spheres):
        images.append(sphere_images(poses, intr, centre, radius))
        c2w.append(poses)
        params.append(torch.full((len(dirs), 1), float(k)))
        views.append(torch.arange(len(dirs)))
    axes = (ParamAxis("k", 0.0, float(len(spheres) - 1), tuple(float(k) for k in range(len(spheres))), 0.0),) if len(spheres) > 1 else ()
    p = torch.cat(params) if len(spheres) > 1 else torch.zeros(len(dirs), 0)
    return SceneData(torch.cat(images), torch.cat(c2w), intr, p, axes, torch.cat(views), background=(1.0, 1.0, 1.0))


def distances(centre: tuple[float, float, float]) -> torch.Tensor:
    return torch.linalg.norm(cell_centres_flat(BOX, (RES,) * 3) - torch.tensor(centre), dim=-1).reshape((RES,) * 3)


def test_no_cell_of_a_sphere_is_carved_and_far_space_is() -> None:
    centre, radius = (0.1, -0.05, 0.0), 0.25
    grid = carve_occupancy(make_scene([(centre, radius)]), BOX, (RES,) * 3)
    dist = distances(centre)
    half_diag = 0.5 * math.sqrt(3) * 1.2 / RES
    assert grid[dist <= radius + half_diag].all(), "a cell touching the sphere was carved"
    # The visual hull of 42 views is close to the sphere: nothing beyond 0.25 of extra radius.
    assert not grid[dist > radius + 0.25].any()
    assert grid.float().mean() < 0.35


def test_union_over_settings_keeps_content_seen_at_one_setting_only() -> None:
    a, b = ((-0.3, 0.0, 0.0), 0.15), ((0.3, 0.2, 0.0), 0.15)
    scene = make_scene([a, b])
    grid = carve_occupancy(scene, BOX, (RES,) * 3)
    half_diag = 0.5 * math.sqrt(3) * 1.2 / RES
    for centre, radius in (a, b):
        assert grid[distances(centre) <= radius + half_diag].all()
    # Each setting alone keeps only its own sphere.
    only_a = carve_occupancy(scene.subset(torch.arange(42)), BOX, (RES,) * 3)
    assert not only_a[distances(b[0]) <= b[1]].any()


def test_empty_images_carve_everything_and_full_images_nothing_seen() -> None:
    scene = make_scene([((0.0, 0.0, 0.0), 0.2)])
    empty = SceneData(torch.full_like(scene.images, 255), scene.c2w, scene.intrinsics, scene.params,
                      scene.param_axes, scene.view_ids)
    assert not carve_occupancy(empty, BOX, (RES,) * 3).any()
    full = SceneData(torch.zeros_like(scene.images), scene.c2w, scene.intrinsics, scene.params,
                     scene.param_axes, scene.view_ids)
    grid = carve_occupancy(full, BOX, (RES,) * 3)
    assert grid[distances((0.0, 0.0, 0.0)) < 0.5].all()


def test_foreground_tolerance_and_dilation() -> None:
    img = torch.full((1, 9, 9, 3), 255, dtype=torch.uint8)
    img[0, 4, 4] = torch.tensor([253, 255, 255], dtype=torch.uint8)  # within tolerance 2
    assert not foreground_masks(img, (1.0, 1.0, 1.0), 2, 0).any()
    img[0, 4, 4] = torch.tensor([252, 255, 255], dtype=torch.uint8)
    mask = foreground_masks(img, (1.0, 1.0, 1.0), 2, 1)[0]
    assert mask.sum() == 9 and mask[3:6, 3:6].all()


def test_setting_groups() -> None:
    params = torch.tensor([[0.0], [1.0], [0.0], [1.0], [2.0]])
    groups = sorted(tuple(g.tolist()) for g in setting_groups(params))
    assert groups == [(0, 2), (1, 3), (4,)]
    assert setting_groups(torch.zeros(3, 0))[0].tolist() == [0, 1, 2]


@pytest.mark.parametrize("radius", [0.02])
def test_structure_thinner_than_a_cell_survives(radius: float) -> None:
    centre = (0.013, 0.21, -0.17)
    grid = carve_occupancy(make_scene([(centre, radius)], size=64), BOX, (RES,) * 3)
    assert grid[distances(centre) <= radius + 0.5 * math.sqrt(3) * 1.2 / RES].all()


def test_cells_few_views_see_do_not_stretch_the_hull() -> None:
    """A box much wider than the views' frusta: its corners are seen by a minority of views, each
    looking through them at the sphere, so counting every view that sees a cell keeps them (as on
    Nyx); requiring three quarters of the views keeps only the sphere's hull, and all of it."""
    box = torch.tensor([[-1.0] * 3, [1.0] * 3])
    centre, radius = (0.0, 0.0, 0.0), 0.55
    scene = make_scene([(centre, radius)])
    dist = torch.linalg.norm(cell_centres_flat(box, (RES,) * 3) - torch.tensor(centre), dim=-1).reshape((RES,) * 3)
    touching = dist <= radius + 0.5 * math.sqrt(3) * 2.0 / RES
    loose = carve_occupancy(scene, box, (RES,) * 3, min_seen_fraction=0.0)
    assert float(dist[loose].max()) > 1.2, "the corners survive when any view may vouch for them"
    tight = carve_occupancy(scene, box, (RES,) * 3, min_seen_fraction=0.75)
    assert tight[touching].all(), "a cell touching the sphere was dropped"
    assert float(dist[tight].max()) < radius + 0.35
    with pytest.raises(ValueError, match="min_seen_fraction"):
        carve_occupancy(scene, box, (RES,) * 3, min_seen_fraction=1.5)
