"""Pinhole and orthographic cameras in the NeRF-Blender convention.

Conventions (shared by the data loader, the model's renderer, the synthetic scenes and the server):
- ``c2w`` is a 4x4 camera-to-world matrix with OpenGL camera axes: the camera looks down its -z,
  +y is up in the image, +x is right.
- Pixel (u, v) has its centre at (u + 0.5, v + 0.5); u grows to the right, v grows downwards.
- ``fx = 0.5 * width / tan(0.5 * camera_angle_x)``; principal point at the image centre unless given.
- Orthographic cameras (``Intrinsics.orthographic``): every ray runs along the camera's -z, from the
  point of the plane through the camera's position that the pixel covers; ``fx`` and ``fy`` are
  pixels per world unit (``height / view_height``).
- Orbit cameras: world +y is up; azimuth 0, elevation 0 puts the camera on +z looking at the
  target; azimuth turns towards +x; elevation 90 looks straight down from +y.
"""

import math
from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels, or an orthographic camera's scale in pixels per world unit."""

    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    fx: float
    """Focal length along x, in pixels."""
    fy: float
    """Focal length along y, in pixels."""
    cx: float
    """Principal point x, in pixels from the left edge."""
    cy: float
    """Principal point y, in pixels from the top edge."""
    orthographic: bool = False
    """Parallel projection: ``fx``, ``fy`` are pixels per world unit, not focal lengths."""

    @classmethod
    def from_fov(cls, width: int, height: int, fov_x_rad: float) -> "Intrinsics":
        """Square pixels, centred principal point, horizontal field of view ``fov_x_rad``."""
        if not (0.0 < fov_x_rad < math.pi):
            raise ValueError(f"horizontal field of view must be in (0, pi) radians, got {fov_x_rad}")
        if width < 1 or height < 1:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        focal = 0.5 * width / math.tan(0.5 * fov_x_rad)
        return cls(width, height, focal, focal, 0.5 * width, 0.5 * height)

    @classmethod
    def from_view_height(cls, width: int, height: int, view_height: float) -> "Intrinsics":
        """An orthographic camera whose image spans ``view_height`` world units vertically (square pixels)."""
        if not (math.isfinite(view_height) and view_height > 0.0):
            raise ValueError(f"view height must be a positive number of world units, got {view_height}")
        if width < 1 or height < 1:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        scale = height / view_height
        return cls(width, height, scale, scale, 0.5 * width, 0.5 * height, orthographic=True)

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """The same camera resampled to another image size."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, self.orthographic)

    @property
    def fov_x_deg(self) -> float:
        """Horizontal field of view of a pinhole camera; an orthographic one has none."""
        if self.orthographic:
            raise ValueError("an orthographic camera has no field of view (see view_height)")
        return math.degrees(2.0 * math.atan(0.5 * self.width / self.fx))

    @property
    def view_height(self) -> float:
        """World units the image spans vertically (orthographic cameras only)."""
        if not self.orthographic:
            raise ValueError("a perspective camera has no view height (see fov_x_deg)")
        return self.height / self.fy

    def pixel_size(self, depth: float) -> float:
        """World size of one pixel at ``depth`` along the view axis (the larger of its two sides)."""
        size = 1.0 / min(self.fx, self.fy)
        return size if self.orthographic else depth * size


def pixel_directions_camera(
    intrinsics: Intrinsics,
    u: Float[Tensor, " n"],
    v: Float[Tensor, " n"],
) -> Float[Tensor, "n 3"]:
    """Unnormalised ray directions in camera axes for pixel coordinates (u, v) (centre = +0.5)."""
    x = (u - intrinsics.cx) / intrinsics.fx
    y = -(v - intrinsics.cy) / intrinsics.fy
    return torch.stack([x, y, -torch.ones_like(x)], dim=-1)


def rays_from_pixels(
    c2w: Float[Tensor, "n 4 4"],
    intrinsics: Intrinsics,
    u: Float[Tensor, " n"],
    v: Float[Tensor, " n"],
) -> tuple[Float[Tensor, "n 3"], Float[Tensor, "n 3"]]:
    """World-space ray origins and unit directions through the given pixel positions.

    ``u`` and ``v`` are continuous pixel coordinates: the centre of pixel (i, j) is (i + 0.5, j + 0.5).
    Pinhole rays start at the camera; orthographic ones on the plane through it, facing its -z.
    Differentiable in ``c2w``.
    """
    dirs_cam = pixel_directions_camera(intrinsics, u, v)  # [n, 3]
    rotation = c2w[:, :3, :3]  # [n, 3, 3]
    if intrinsics.orthographic:
        offsets = torch.stack([dirs_cam[:, 0], dirs_cam[:, 1], torch.zeros_like(u)], dim=-1)  # [n, 3], plane
        rays_o = c2w[:, :3, 3] + torch.einsum("nij,nj->ni", rotation, offsets)
        rays_d = -rotation[:, :, 2]
        return rays_o, rays_d / torch.linalg.norm(rays_d, dim=-1, keepdim=True).clamp_min(1e-12)
    rays_d = torch.einsum("nij,nj->ni", rotation, dirs_cam)  # [n, 3]
    rays_d = rays_d / torch.linalg.norm(rays_d, dim=-1, keepdim=True).clamp_min(1e-12)
    rays_o = c2w[:, :3, 3]  # [n, 3]
    return rays_o, rays_d


def image_rays(
    c2w: Float[Tensor, "4 4"], intrinsics: Intrinsics, rows: tuple[int, int] | None = None
) -> tuple[Float[Tensor, "h w 3"], Float[Tensor, "h w 3"]]:
    """Rays through every pixel centre of one image, row-major (v, u); ``rows = (start, stop)``:
    those of image rows ``start`` to ``stop - 1`` only (``h = stop - start``)."""
    start, stop = (0, intrinsics.height) if rows is None else rows
    if not 0 <= start < stop <= intrinsics.height:
        raise ValueError(f"rows {start}..{stop} are not within the image's {intrinsics.height} rows")
    h, w = stop - start, intrinsics.width
    vv, uu = torch.meshgrid(
        torch.arange(start, stop, dtype=c2w.dtype, device=c2w.device) + 0.5,
        torch.arange(w, dtype=c2w.dtype, device=c2w.device) + 0.5,
        indexing="ij",
    )
    rays_o, rays_d = rays_from_pixels(
        c2w.expand(h * w, 4, 4), intrinsics, uu.reshape(-1), vv.reshape(-1)
    )
    return rays_o.reshape(h, w, 3), rays_d.reshape(h, w, 3)


def project_points(
    c2w: Float[Tensor, "4 4"], intrinsics: Intrinsics, points: Float[Tensor, "n 3"]
) -> tuple[Float[Tensor, "n 2"], Float[Tensor, " n"]]:
    """Pixel coordinates (u, v) and depth along the viewing axis of world points."""
    rotation, origin = c2w[:3, :3], c2w[:3, 3]
    local = (points - origin) @ rotation  # [n, 3], world -> camera
    depth = -local[:, 2]
    safe = torch.ones_like(depth) if intrinsics.orthographic else depth.clamp_min(1e-12)
    u = intrinsics.cx + intrinsics.fx * local[:, 0] / safe
    v = intrinsics.cy - intrinsics.fy * local[:, 1] / safe
    return torch.stack([u, v], dim=-1), depth


def orbit_c2w(
    azimuth_deg: float,
    elevation_deg: float,
    distance: float,
    target: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> np.ndarray:
    """Camera-to-world matrix (float64, 4x4) of a camera orbiting ``target`` and looking at it.

    Well defined at the poles: the camera's x axis is the azimuth tangent, so elevation +-90 keeps
    a continuous image orientation.
    """
    for name, value in (("azimuth", azimuth_deg), ("elevation", elevation_deg), ("distance", distance)):
        if not math.isfinite(value):
            raise ValueError(f"{name} must be finite, got {value}")
    if distance <= 0:
        raise ValueError(f"distance must be positive, got {distance}")
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    back = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    right = np.array([math.cos(az), 0.0, -math.sin(az)])
    up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2] = right, up, back
    c2w[:3, 3] = np.asarray(target, dtype=np.float64) + distance * back
    return c2w


def frame_c2w(position: np.ndarray, direction: np.ndarray, up: np.ndarray, what: str = "camera") -> np.ndarray:
    """Camera-to-world matrix (float64, 4x4) of a camera at ``position`` looking along ``direction``
    with its image's up as near ``up`` as the direction allows; ValueError naming ``what`` otherwise."""
    position, direction, up = (np.asarray(x, dtype=np.float64).reshape(3) for x in (position, direction, up))
    length = float(np.linalg.norm(direction))
    if not (math.isfinite(length) and length > 1e-12):
        raise ValueError(f"{what}: the view direction is zero (the camera sits on its target)")
    back = -direction / length
    right = np.cross(up, back)
    up_length = float(np.linalg.norm(up))
    if not (math.isfinite(up_length) and up_length > 1e-12) or np.linalg.norm(right) <= 1e-6 * up_length:
        raise ValueError(f"{what}: the up vector {up.tolist()} is zero or parallel to the view direction")
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, position
    return c2w


def orbit_from_c2w(c2w: np.ndarray, target: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> tuple[float, float, float]:
    """(azimuth_deg, elevation_deg, distance) of a camera position around ``target``."""
    offset = np.asarray(c2w, dtype=np.float64)[:3, 3] - np.asarray(target, dtype=np.float64)
    distance = float(np.linalg.norm(offset))
    if distance <= 0:
        raise ValueError("camera sits on the orbit target")
    x, y, z = offset / distance
    return math.degrees(math.atan2(x, z)), math.degrees(math.asin(max(-1.0, min(1.0, y)))), distance


def check_rigid_c2w(c2w: np.ndarray, tol: float = 1e-3) -> np.ndarray:
    """Validate a camera-to-world matrix: 4x4, finite, orthonormal rotation, last row (0, 0, 0, 1)."""
    m = np.asarray(c2w, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"c2w must be 4x4, got shape {list(m.shape)}")
    if not np.all(np.isfinite(m)):
        raise ValueError("c2w has non-finite entries")
    if np.max(np.abs(m[3] - np.array([0.0, 0.0, 0.0, 1.0]))) > tol:
        raise ValueError("c2w last row must be [0, 0, 0, 1]")
    rotation = m[:3, :3]
    if np.max(np.abs(rotation.T @ rotation - np.eye(3))) > tol or np.linalg.det(rotation) < 0:
        raise ValueError("c2w rotation part is not a proper rotation (orthonormal, determinant +1)")
    return m
