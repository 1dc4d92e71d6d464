"""The reference renderer against closed forms (DVR integral, opacity correction, sphere isosurface)."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from visnerf.data.cameras import Intrinsics, image_rays, orbit_c2w
from visnerf.scenes.fields import ConstantField, LinearRampField, RadialDistanceField
from visnerf.scenes.reference_renderer import DvrVolume, IsoVolume, MarchConfig, lit_colours, render_image, render_rays
from visnerf.scenes.transfer_function import TransferFunction, constant_extinction_tf

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # small renders: one thread (conftest)


def _c2w(
    azimuth: float, elevation: float, distance: float, dtype: torch.dtype = torch.float64
) -> torch.Tensor:
    return torch.tensor(orbit_c2w(azimuth, elevation, distance), dtype=dtype)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_homogeneous_box_transmittance_is_exp_minus_sigma_length(dtype: torch.dtype) -> None:
    """Box [-0.4, 0.4] x [-0.3, 0.3] x [-0.25, 0.25] of extinction sigma = 3 seen head-on from +z.

    A ray through the front face z = 0.25 and the back face z = -0.25 travels L = 0.5 / |d_z|, so
    T = exp(-3 L): exp(-1.5) = 0.22313 on the axis. Black medium on white: every channel equals T.
    """
    sigma = 3.0
    box = ((-0.4, -0.3, -0.25), (0.4, 0.3, 0.25))
    volume = DvrVolume(ConstantField(1.0), constant_extinction_tf(sigma), bbox=box)
    intrinsics = Intrinsics.from_fov(33, 33, math.radians(30.0))
    c2w = _c2w(0.0, 0.0, 2.0, dtype)
    out = render_image(volume, c2w, intrinsics, MarchConfig(step=0.01, early_stop_transmittance=0.0))
    rays_o, rays_d = (r.reshape(-1, 3).double() for r in image_rays(c2w, intrinsics))
    t_front = (0.25 - rays_o[:, 2]) / rays_d[:, 2]  # [n]
    t_back = (-0.25 - rays_o[:, 2]) / rays_d[:, 2]
    p_front = rays_o + t_front[:, None] * rays_d
    p_back = rays_o + t_back[:, None] * rays_d
    through = (p_front[:, :2].abs() < torch.tensor([0.4, 0.3], dtype=torch.float64)).all(dim=1) & (
        p_back[:, :2].abs() < torch.tensor([0.4, 0.3], dtype=torch.float64)
    ).all(dim=1)
    assert through.sum() > 200
    expected = torch.exp(-sigma * 0.5 / rays_d[:, 2].abs())  # [n]
    transmittance = 1.0 - out.opacity.double()
    assert torch.allclose(transmittance[through], expected[through], atol=1e-4, rtol=0.0)
    assert abs(float(transmittance[16 * 33 + 16]) - math.exp(-1.5)) < 1e-4  # the axis ray
    assert torch.allclose(out.rgb.double()[through], expected[through, None].expand(-1, 3), atol=1e-4)
    misses = ~((p_front[:, :2].abs() < 0.45).all(dim=1) | (p_back[:, :2].abs() < 0.45).all(dim=1))
    assert torch.all(out.opacity[misses] == 0) and torch.all(out.rgb[misses] == 1)


def _ramp_transmittance(step: float) -> torch.Tensor:
    """Rays from (0, 0, 2) through the ramp v = z + 0.5 in the unit box, for a given step."""
    alpha_max, reference_step = 0.6, 0.25
    black = (0.0, 0.0, 0.0)
    tf = TransferFunction((0.0, 1.0), (black, black), (0.0, alpha_max), reference_step)
    volume = DvrVolume(LinearRampField((0.0, 0.0, 1.0), 0.5), tf)
    slopes = torch.tensor([[0.0, 0.0], [0.1, 0.0], [0.0, -0.15], [0.12, 0.12]], dtype=torch.float64)
    rays_d = torch.cat([slopes, -torch.ones(4, 1, dtype=torch.float64)], dim=1)
    rays_d = rays_d / torch.linalg.norm(rays_d, dim=1, keepdim=True)
    rays_o = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64).expand(4, 3)
    out = render_rays(volume, rays_o, rays_d, MarchConfig(step=step, early_stop_transmittance=0.0))
    return out.rgb[:, 1]  # green = transmittance for a black medium on white


def _ramp_exact() -> torch.Tensor:
    """Closed form for ``_ramp_transmittance``.

    sigma(v) = -ln(1 - a v) / dt0 with a = 0.6, dt0 = 0.25; along a ray entering z = 0.5 and leaving
    z = -0.5 the value falls from 1 to 0 at rate |d_z| per unit length, so
    tau = (1 / |d_z|) * (1 / dt0) * int_0^1 -ln(1 - a v) dv = (1 + (1 - a) ln(1 - a) / a) / (dt0 |d_z|);
    on the axis tau = 4 * (1 + 0.4 ln 0.4 / 0.6) = 1.556544, T = 0.210861.
    """
    a, dt0 = 0.6, 0.25
    tau_axis = (1.0 + (1.0 - a) * math.log(1.0 - a) / a) / dt0
    slopes = torch.tensor([[0.0, 0.0], [0.1, 0.0], [0.0, -0.15], [0.12, 0.12]], dtype=torch.float64)
    cos_z = 1.0 / torch.sqrt(1.0 + slopes.square().sum(dim=1))  # |d_z|
    return torch.exp(-tau_axis / cos_z)


def test_ramp_integral_matches_closed_form() -> None:
    """The fine-step transmittance of the ramp agrees with the closed form to 1e-6."""
    assert abs(_ramp_exact()[0].item() - 0.210861) < 1e-6
    assert torch.allclose(_ramp_transmittance(1.0 / 512.0), _ramp_exact(), atol=1e-6, rtol=0.0)


def test_discrete_integral_error_falls_at_second_order_as_step_halves() -> None:
    """Error of the ramp's transmittance for steps 1/4 ... 1/64 (float64).

    Midpoint samples make the quadrature second order: the measured order log2(e(h) / e(h/2)) is
    2.00 (1.99 - 2.00 over these steps); the requirement is at least linear (>= 1), asserted >= 1.8.
    """
    exact = _ramp_exact()
    errors = [(_ramp_transmittance(1.0 / n) - exact).abs().max().item() for n in (4, 8, 16, 32, 64)]
    orders = [math.log2(e0 / e1) for e0, e1 in zip(errors, errors[1:], strict=False)]
    assert errors[-1] < 1e-4
    assert all(order >= 1.8 for order in orders), orders
    assert all(order <= 2.2 for order in orders), orders


def _blob_volume(reference_step: float) -> DvrVolume:
    """A smooth ball: opacity and colour fall with the distance to the centre."""
    red, orange, blue = (0.9, 0.1, 0.1), (1.0, 0.6, 0.1), (0.1, 0.3, 0.9)
    tf = TransferFunction(
        (0.0, 0.15, 0.3, 0.45), (red, orange, blue, blue), (0.3, 0.15, 0.04, 0.0), reference_step
    )
    return DvrVolume(RadialDistanceField(), tf, support_radius=0.5)


def test_opacity_correction_makes_the_image_independent_of_the_step() -> None:
    """Steps 1/128, 1/256 and 1/512 give the same image to 1e-3 (max over pixels and channels).

    Without correction (the TF opacity applied per sample, i.e. reference_step = step) the images
    differ by far more, which is what the correction removes.
    """
    intrinsics = Intrinsics.from_fov(24, 24, math.radians(30.0))
    c2w = _c2w(30.0, 20.0, 2.0)
    images = {
        n: render_image(_blob_volume(0.01), c2w, intrinsics, MarchConfig(step=1.0 / n)).rgb
        for n in (128, 256, 512)
    }
    assert (images[128] - images[512]).abs().max() < 1e-3
    assert (images[256] - images[512]).abs().max() < 1e-3
    naive = {
        n: render_image(_blob_volume(1.0 / n), c2w, intrinsics, MarchConfig(step=1.0 / n)).rgb
        for n in (128, 256)
    }
    assert (naive[128] - naive[256]).abs().max() > 0.05


def test_sphere_isosurface_has_the_analytic_silhouette_and_depth() -> None:
    """Isosurface r = 0.3 of the distance field seen from distance 2 at an oblique orbit angle.

    Silhouette: half-angle asin(r / d), radius f tan(asin(0.15)) = 0.15168 f pixels around the
    principal point (f = 32.5 / tan 15 deg = 121.29 px, radius 18.40 px); every pixel centre more
    than one pixel inside it is hit, none more than one pixel outside. Depth: the nearer root of
    |o + t d| = r, to well within a pixel's footprint.
    """
    radius, distance, size = 0.3, 2.0, 65
    intrinsics = Intrinsics.from_fov(size, size, math.radians(30.0))
    c2w = _c2w(35.0, 20.0, distance)
    volume = IsoVolume(RadialDistanceField(), radius)
    out = render_image(volume, c2w, intrinsics, MarchConfig(step=1.0 / 128.0))
    hit = (out.opacity > 0).reshape(size, size)
    silhouette = intrinsics.fx * math.tan(math.asin(radius / distance))
    assert abs(silhouette - 18.40) < 0.01
    v, u = torch.meshgrid(torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="ij")
    from_centre = torch.sqrt((u - intrinsics.cx) ** 2 + (v - intrinsics.cy) ** 2)
    assert torch.all(hit[from_centre < silhouette - 1.0])
    assert not torch.any(hit[from_centre > silhouette + 1.0])
    assert abs(math.sqrt(hit.sum().item() / math.pi) - silhouette) < 1.0
    rays_o, rays_d = (r.reshape(-1, 3) for r in image_rays(c2w, intrinsics))
    b = (rays_o * rays_d).sum(dim=1)
    disc = b.square() - (rays_o.square().sum(dim=1) - radius**2)
    exact = -b - torch.sqrt(disc.clamp_min(0.0))
    mask = hit.reshape(-1)
    assert torch.all(disc[mask] >= -1e-9)
    pixel_footprint = distance / intrinsics.fx
    assert (out.depth[mask] - exact[mask]).abs().max() < 1e-3 * pixel_footprint
    assert torch.all(torch.isinf(out.depth[~mask]))


def test_sphere_shading_is_brightest_facing_the_headlight() -> None:
    """Blinn-Phong from a headlight: the centre pixel (normal towards the eye) is the brightest."""
    intrinsics = Intrinsics.from_fov(33, 33, math.radians(30.0))
    out = render_image(IsoVolume(RadialDistanceField(), 0.3), _c2w(0.0, 0.0, 2.0), intrinsics, MarchConfig())
    brightness = out.rgb.sum(dim=1).reshape(33, 33)
    brightness[out.opacity.reshape(33, 33) == 0] = 0.0
    row, col = np.unravel_index(int(torch.argmax(brightness)), (33, 33))
    assert abs(row - 16) <= 1 and abs(col - 16) <= 1


def test_early_stop_and_chunking_do_not_change_the_result() -> None:
    """Chunked rendering equals one chunk; early stopping changes colours by < the stop threshold."""
    intrinsics = Intrinsics.from_fov(20, 20, math.radians(30.0))
    c2w = _c2w(-40.0, 10.0, 2.0)
    base = MarchConfig(step=1.0 / 128.0, chunk_rays=4096, early_stop_transmittance=0.0)
    whole = render_image(_blob_volume(0.01), c2w, intrinsics, base)
    chunked = render_image(_blob_volume(0.01), c2w, intrinsics, dataclasses.replace(base, chunk_rays=37))
    stopped = render_image(
        _blob_volume(0.01), c2w, intrinsics, dataclasses.replace(base, early_stop_transmittance=1e-4)
    )
    assert torch.allclose(whole.rgb, chunked.rgb, atol=1e-6)
    assert (whole.rgb - stopped.rgb).abs().max() < 2e-4


def test_lit_colours_follow_blinn_phong_about_the_gradient() -> None:
    """A ramp's gradient is known: seen along it, a sample takes the full diffuse light and the
    highlight; seen at 60 degrees to it, cos = 1/2 (two-sided: from behind as well); where the
    extinction is zero the colour stays the transfer function's."""
    config = MarchConfig()
    s = config.shading
    points = torch.zeros(4, 3, dtype=torch.float64)
    half = math.sqrt(3.0) / 2.0
    rays_d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [half, 0.0, 0.5], [half, 0.0, 0.5]], dtype=torch.float64)
    colour = torch.full((4, 3), 0.5, dtype=torch.float64)
    sigma = torch.tensor([1.0, 1.0, 1.0, 0.0], dtype=torch.float64)
    lit = lit_colours(LinearRampField((0.0, 0.0, 2.0)), points, rays_d, colour, sigma, config)
    full = 0.5 * (s.ambient + s.diffuse) + s.specular
    oblique = 0.5 * (s.ambient + 0.5 * s.diffuse) + s.specular * 0.5**s.shininess
    expected = torch.tensor([full, full, oblique, 0.5], dtype=torch.float64)[:, None].expand(4, 3)
    assert torch.allclose(lit, expected.clamp(0.0, 1.0), atol=1e-9)
