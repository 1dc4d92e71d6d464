"""Orthographic cameras against closed forms, and the look-at frame of producers' cameras."""

import math

import numpy as np
import pytest
import torch

from visnerf.data.cameras import Intrinsics, frame_c2w, image_rays, orbit_c2w, project_points


def test_view_height_scale_and_pixel_size() -> None:
    k = Intrinsics.from_view_height(40, 20, 2.0)
    assert k.orthographic and k.fx == k.fy == 10.0 and k.view_height == pytest.approx(2.0)
    assert k.pixel_size(5.0) == pytest.approx(0.1) and k.pixel_size(50.0) == pytest.approx(0.1)
    assert k.scaled(80, 40).view_height == pytest.approx(2.0) and k.scaled(80, 40).orthographic
    with pytest.raises(ValueError, match="no field of view"):
        _ = k.fov_x_deg
    with pytest.raises(ValueError, match="positive"):
        Intrinsics.from_view_height(4, 4, 0.0)
    pinhole = Intrinsics.from_fov(40, 20, math.radians(60))
    assert pinhole.pixel_size(2.0) == pytest.approx(2.0 / pinhole.fx)
    with pytest.raises(ValueError, match="no view height"):
        _ = pinhole.view_height


def test_orthographic_rays_are_parallel_and_start_on_the_plane() -> None:
    c2w = torch.tensor(orbit_c2w(35.0, 20.0, 3.0), dtype=torch.float64)
    k = Intrinsics.from_view_height(6, 4, 2.0)  # 3 world units wide, 2 high
    o, d = image_rays(c2w, k)
    forward = -c2w[:3, 2]
    assert torch.allclose(d, forward.expand_as(d), atol=1e-12)
    right, up, centre = c2w[:3, 0], c2w[:3, 1], c2w[:3, 3]
    for v in range(4):
        for u in range(6):
            x = (u + 0.5 - 3.0) / k.fx
            y = -(v + 0.5 - 2.0) / k.fy
            assert torch.allclose(o[v, u], centre + x * right + y * up, atol=1e-12)
    # corners of the image span the view: 3 x 2 world units less half a pixel each side
    assert float(torch.linalg.norm(o[0, 0] - o[0, -1])) == pytest.approx(3.0 - 0.5)
    assert float(torch.linalg.norm(o[0, 0] - o[-1, 0])) == pytest.approx(2.0 - 0.5)


def test_orthographic_projection_inverts_the_rays() -> None:
    c2w = torch.tensor(orbit_c2w(-70.0, 40.0, 2.5), dtype=torch.float64)
    k = Intrinsics.from_view_height(16, 16, 1.5)
    o, d = image_rays(c2w, k)
    points = (o + 0.7 * d).reshape(-1, 3)
    uv, depth = project_points(c2w, k, points)
    vv, uu = torch.meshgrid(torch.arange(16.0) + 0.5, torch.arange(16.0) + 0.5, indexing="ij")
    assert torch.allclose(uv[:, 0], uu.reshape(-1).double(), atol=1e-9)
    assert torch.allclose(uv[:, 1], vv.reshape(-1).double(), atol=1e-9)
    assert torch.allclose(depth, torch.full_like(depth, 0.7), atol=1e-12)


def test_look_at_accepts_an_up_vector_not_orthogonal_to_the_view() -> None:
    position, target = np.array([1.0, 2.0, 3.0]), np.array([0.2, -0.1, 0.4])
    c2w = frame_c2w(position, target - position, np.array([0.1, 1.0, 0.3]))
    rotation = c2w[:3, :3]
    assert np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-12) and np.linalg.det(rotation) > 0
    forward = (target - position) / np.linalg.norm(target - position)
    assert np.allclose(-c2w[:3, 2], forward, atol=1e-12)
    assert c2w[:3, 1] @ np.array([0.1, 1.0, 0.3]) > 0  # the image's up leans the way it was asked
    assert np.allclose(frame_c2w(np.array([0, 0, 2.0]), np.array([0, 0, -2.0]), np.array([0, 1.0, 0])),
                       orbit_c2w(0.0, 0.0, 2.0), atol=1e-12)


@pytest.mark.parametrize("up", [np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -3.0]), np.zeros(3)])
def test_up_parallel_to_the_view_is_refused(up) -> None:
    with pytest.raises(ValueError, match="parallel to the view direction"):
        frame_c2w(np.zeros(3), np.array([0.0, 0.0, 1.0]), up, "row 7")


def test_camera_on_its_target_is_refused() -> None:
    with pytest.raises(ValueError, match="sits on its target"):
        frame_c2w(np.ones(3), np.zeros(3), np.array([0.0, 1.0, 0.0]))
