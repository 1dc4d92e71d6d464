"""Written datasets agree with the camera model of ``visnerf.data.cameras`` (projection and rays)."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from visnerf.data.cameras import Intrinsics, project_points, rays_from_pixels
from visnerf.scenes.catalog import SceneSpec
from visnerf.scenes.fields import RadialDistanceField
from visnerf.scenes.reference_renderer import IsoVolume
from visnerf.scenes.writer import DatasetOptions, write_scene

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # small renders: one thread (conftest)


POINT = (0.21, -0.12, 0.17)


def _dot_scene() -> SceneSpec:
    """A small sphere (radius 0.03) around ``POINT``, the only thing in the volume."""
    return SceneSpec(
        "dot", "A dot", "ir", lambda: IsoVolume(RadialDistanceField(POINT), 0.03), step=1.0 / 128.0
    )


def test_world_point_projects_where_the_camera_model_says_and_the_ray_returns(tmp_path: Path) -> None:
    """In every written view the pixel the camera model predicts for the dot's centre is covered,
    the dot's image centroid lies within half a pixel of the projection, and the ray that
    ``rays_from_pixels`` casts through the projection passes the centre within 1e-4.

    The projection of a ball's centre and the centroid of its image differ only to second order in
    radius / distance (about 0.02 px here); the rest is the pixel grid (the dot is ~2.5 px across).
    """
    write_scene(
        _dot_scene(), tmp_path, DatasetOptions(resolution=96, n_views=12, n_test_views=3), progress=False
    )
    document = json.loads((tmp_path / "transforms_train.json").read_text())
    assert len(document["frames"]) == 12
    point = torch.tensor([POINT], dtype=torch.float64)
    for frame in document["frames"] + json.loads((tmp_path / "transforms_test.json").read_text())["frames"]:
        image = np.asarray(Image.open(tmp_path / f"{frame['file_path']}.png"))
        assert image.shape == (96, 96, 3) and image.dtype == np.uint8
        intrinsics = Intrinsics.from_fov(image.shape[1], image.shape[0], document["camera_angle_x"])
        c2w = torch.tensor(frame["transform_matrix"], dtype=torch.float64)
        uv, depth = project_points(c2w, intrinsics, point)
        assert depth.item() > 0
        covered = image.min(axis=2) < 255  # [h, w] pixels that see the dot
        assert 4 <= covered.sum() < 100
        rows, cols = np.nonzero(covered)
        centroid = np.array([cols.mean() + 0.5, rows.mean() + 0.5])
        assert np.abs(centroid - uv[0].numpy()).max() < 0.5, (frame["file_path"], centroid, uv)
        assert covered[int(uv[0, 1]), int(uv[0, 0])]
        rays_o, rays_d = rays_from_pixels(c2w[None], intrinsics, uv[:, 0], uv[:, 1])
        to_point = point - rays_o
        along = (to_point * rays_d).sum(dim=1, keepdim=True)
        assert torch.linalg.norm(to_point - along * rays_d).item() < 1e-4
        assert abs(along.item() - math.dist(c2w[:3, 3].tolist(), POINT)) < 1e-3
