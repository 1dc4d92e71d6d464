"""The fast renderer (occupancy skipping, early termination, colour only where the weight matters)
against the exhaustive one on stiff content: a thin opaque shell, a tenth of an occupancy cell
thick, and rays that graze the box. The density is analytic, so the occupancy grid is built from
it the way training builds it (``build_occupancy``) and has to catch content that passes between
cell centres (a grid from cell centres alone misses parts of this shell)."""

import math
from dataclasses import replace

import pytest
import torch

from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.occupancy import build_occupancy
from visnerf.rendering.render_settings import RenderSettings
from visnerf.rendering.renderer import march_rays, render_image
from visnerf.representation.field import VisNerfField
from visnerf.representation.frame_field import FrameField
from visnerf.testing import make_tiny_field

RADIUS, WIDTH, SIGMA = 0.3, 1.0 / 120.0, 2000.0  # a cell is 1/12 wide: the shells are a tenth of that


def shell_density(points: torch.Tensor) -> torch.Tensor:
    """A Gaussian spherical shell and, beside it, a flat sheet at z = 0, halfway between two layers
    of cell centres (the nearest centre is half a cell, five widths, away). Optical depth across
    either: SIGMA * WIDTH * sqrt(pi) = 30, opaque."""
    sphere = torch.exp(-(((points.norm(dim=-1) - RADIUS) / WIDTH) ** 2))
    inside = (points[:, 0] > 0.32) & (points[:, 0] < 0.48) & (points[:, 1].abs() < 0.2)
    sheet = torch.where(inside, torch.exp(-((points[:, 2] / WIDTH) ** 2)), 0.0)
    return SIGMA * torch.maximum(sphere, sheet)


@pytest.fixture()
def shell_field(monkeypatch: pytest.MonkeyPatch):
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=5, resolution=12)
    monkeypatch.setattr(VisNerfField, "density", lambda self, points, q: shell_density(points))
    monkeypatch.setattr(FrameField, "density_at", lambda self, samples: shell_density(samples.points))
    return field.eval()


def _occupancy(field: VisNerfField, step: float) -> torch.Tensor:
    settings = torch.tensor([[-1.0], [1.0]])
    return build_occupancy(field, (12, 12, 12), settings, step, threshold=1e-4)


def test_the_occupancy_grid_keeps_a_shell_a_tenth_of_a_cell_thick(shell_field) -> None:
    step = shell_field.voxel_size() * 0.5
    grid = _occupancy(shell_field, step)
    # Every point of the shell and of the sheet lies in an occupied cell.
    g = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(4000, 3, generator=g), dim=-1)
    sheet = torch.cat([torch.rand(2000, 1, generator=g) * 0.15 + 0.325, torch.rand(2000, 1, generator=g) * 0.38 - 0.19,
                       torch.zeros(2000, 1)], dim=1)
    from visnerf.rendering.occupancy import query_occupancy

    assert query_occupancy(grid, shell_field.aabb, dirs * RADIUS).all()
    assert query_occupancy(grid, shell_field.aabb, sheet).all()
    assert 0.05 < float(grid.float().mean()) < 0.9  # and it does skip something


@pytest.mark.parametrize(("azimuth", "first_segment", "segment"), [(0.0, 16, 16), (33.0, 16, 16), (33.0, 3, 64)])
def test_fast_frames_match_the_exhaustive_frames_on_a_thin_opaque_shell(
    shell_field, azimuth: float, first_segment: int, segment: int
) -> None:
    """Segments of one length, and segments growing from 3 samples (3, 6, 12, ... 64)."""
    exhaustive = RenderSettings(use_occupancy=False, early_termination=False, weight_threshold_per_voxel=0.0,
                                step_ratio=0.25)
    fast = replace(exhaustive, use_occupancy=True, early_termination=True, weight_threshold_per_voxel=1e-4,
                   early_stop_eps=1e-4, segment_samples=segment, first_segment_samples=first_segment)
    shell_field.set_occupancy(_occupancy(shell_field, shell_field.voxel_size() * 0.25))
    intr = Intrinsics.from_fov(40, 40, math.radians(35.0))
    c2w = torch.from_numpy(orbit_c2w(azimuth, 20.0, 2.0)).float()
    params = torch.tensor([0.3])
    with torch.inference_mode():
        a = render_image(shell_field, c2w, intr, params, exhaustive)
        b = render_image(shell_field, c2w, intr, params, fast)
    opacity_seen = (a - 1.0).abs().amax(-1) > 0.05
    assert opacity_seen.float().mean() > 0.1  # the shell is in the picture
    # Early termination drops at most the 1e-4 of light left, skipped weights at most 1e-4 each.
    assert float((a - b).abs().max()) < 2e-3


def test_rays_grazing_the_box_match_the_exhaustive_march(shell_field) -> None:
    """Origins on the faces and edges of the box, directions along the faces, and rays that touch
    the box at a corner only: the fast march equals the exhaustive one, and is finite."""
    shell_field.set_occupancy(_occupancy(shell_field, shell_field.voxel_size() * 0.5))
    lo, hi = shell_field.aabb
    origins, dirs = [], []
    for y in torch.linspace(float(lo[1]), float(hi[1]), 7):
        origins.append([float(lo[0]), float(y), -1.0])  # on the face x = lo, running along z
        dirs.append([0.0, 0.0, 1.0])
        origins.append([-1.0, float(y), float(hi[2])])  # on the face z = hi, running along x
        dirs.append([1.0, -0.0, 0.0])
    # an edge, the corner diagonal, through the sheet, beside the shell (near-tangent), the centre
    origins += [[float(lo[0]), float(lo[1]), -1.0], [-1.0, -1.0, -1.0], [0.4, 0.05, -1.0], [0.29, 0.0, -1.0],
                [0.0, 0.0, -1.0]]
    dirs += [[0.0, 0.0, 1.0], [1.0, 1.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]
    rays_o = torch.tensor(origins)
    rays_d = torch.nn.functional.normalize(torch.tensor(dirs), dim=-1)
    q_d, q_a = shell_field.param_features(torch.tensor([[0.0]]))
    frame = FrameField(shell_field, q_d, q_a)
    bg = torch.ones(3)
    exhaustive = RenderSettings(use_occupancy=False, early_termination=False, weight_threshold_per_voxel=0.0)
    fast = replace(exhaustive, early_termination=True, weight_threshold_per_voxel=1e-4, segment_samples=8)
    with torch.inference_mode():
        a = march_rays(shell_field, rays_o, rays_d, frame, bg, exhaustive, None)
        b = march_rays(shell_field, rays_o, rays_d, frame, bg, fast, EmptySpace.of(shell_field.occupancy, shell_field.aabb))
    assert torch.isfinite(a).all() and torch.isfinite(b).all()
    assert float((a - b).abs().max()) < 2e-3
    assert float((a[-1] - 1.0).abs().max()) > 0.05  # the ray through the centre meets the shell
    assert float((a[-3] - 1.0).abs().max()) > 0.05  # and the one through the sheet meets the sheet


def _haze_density(points: torch.Tensor) -> torch.Tensor:
    """The opaque shell wrapped in a faint haze out to radius 0.45 (optical depth 0.03 in front
    of the shell): at a quarter-voxel step every haze sample weighs below 4.2e-3."""
    r = points.norm(dim=-1)
    return shell_density(points) + 0.2 * ((r > RADIUS) & (r < 0.45)).float()


def test_unshaded_weight_takes_the_mean_colour_of_the_shaded_samples(shell_field, monkeypatch) -> None:
    """Skipping colour below the threshold while giving the skipped weight the ray's mean colour
    is exact for a colour that does not vary, on every ray that meets the shell; giving it black
    (no gain) is off by the skipped weight, the haze in front of the shell."""
    colour = torch.tensor([0.2, 0.6, 0.9])
    monkeypatch.setattr(FrameField, "density_at", lambda self, samples: _haze_density(samples.points))
    monkeypatch.setattr(FrameField, "color_at", lambda self, samples, ray_terms: colour.expand(len(samples), 3))
    import visnerf.rendering.renderer as renderer

    intr = Intrinsics.from_fov(24, 24, math.radians(35.0))
    c2w = torch.from_numpy(orbit_c2w(20.0, 15.0, 2.0)).float()
    params = torch.tensor([0.3])
    exhaustive = RenderSettings(use_occupancy=False, early_termination=False, weight_threshold_per_voxel=0.0, step_ratio=0.25)
    skipping = replace(exhaustive, weight_threshold_per_voxel=2e-2)  # 5e-3 a sample
    with torch.inference_mode():
        a = render_image(shell_field, c2w, intr, params, exhaustive)
        b = render_image(shell_field, c2w, intr, params, skipping)
        monkeypatch.setattr(renderer, "_unshaded_gain", lambda opacity, shaded: torch.ones_like(opacity))
        black = render_image(shell_field, c2w, intr, params, skipping)
    opacity = (1.0 - a[..., 0]) / (1.0 - colour[0])  # background white
    hits = opacity > 0.999
    assert hits.float().mean() > 0.2
    assert float((a - b)[hits].abs().max()) < 1e-5
    assert float((a - black)[hits].abs().max()) > 0.01  # what the gain corrects
    # Rays through the haze alone shade nothing and keep black for its weight, as before.
    assert float((a - b).abs().max()) <= float((a - black).abs().max()) + 1e-6


def test_the_colour_threshold_skips_the_same_part_of_a_medium_at_any_spacing(shell_field, monkeypatch) -> None:
    """A uniform translucent ball (optical depth 3 across): a sample's weight grows with the
    spacing, so a threshold per voxel of spacing skips the same stretch of the medium at a quarter
    and at half a voxel, where one per sample skipped four times less at the coarser spacing. The
    unshaded weight is read from frames with the gain off (it then shows as black)."""
    colour = torch.tensor([0.2, 0.6, 0.9])
    sigma = 3.0 / 0.8
    monkeypatch.setattr(FrameField, "density_at", lambda self, samples: sigma * (samples.points.norm(dim=-1) < 0.4).float())
    monkeypatch.setattr(FrameField, "color_at", lambda self, samples, ray_terms: colour.expand(len(samples), 3))
    import visnerf.rendering.renderer as renderer

    monkeypatch.setattr(renderer, "_unshaded_gain", lambda opacity, shaded: torch.ones_like(opacity))
    intr = Intrinsics.from_fov(8, 8, math.radians(10.0))
    c2w = torch.from_numpy(orbit_c2w(20.0, 15.0, 2.0)).float()
    params = torch.tensor([0.3])

    def unshaded(ratio: float, per_voxel: float) -> torch.Tensor:
        base = RenderSettings(use_occupancy=False, early_termination=False, step_ratio=ratio)
        with torch.inference_mode():
            every = render_image(shell_field, c2w, intr, params, replace(base, weight_threshold_per_voxel=0.0))
            skipping = render_image(shell_field, c2w, intr, params, replace(base, weight_threshold_per_voxel=per_voxel))
        opacity = (1.0 - every[..., 2]) / (1.0 - colour[2])  # white background
        shaded = (skipping[..., 2] - (1.0 - opacity)) / colour[2]
        return (opacity - shaded)[3:5, 3:5]  # the rays through the middle of the ball

    fine, coarse = unshaded(0.25, 0.04), unshaded(0.5, 0.04)
    assert float(fine.min()) > 0.05 and float(coarse.min()) > 0.05
    assert float((fine - coarse).abs().max()) < 0.02
    per_sample = unshaded(0.5, 0.04 * 0.25 / 0.5)  # the fine spacing's threshold, taken per sample
    assert float(per_sample.max()) < 0.5 * float(fine.min())


def test_unshaded_gain_is_guarded() -> None:
    from visnerf.rendering.renderer import _unshaded_gain

    opacity = torch.tensor([0.5, 0.5, 1e-5, 0.0, 0.9])
    shaded = torch.tensor([0.5, 0.25, 0.0, 0.0, 1e-30])
    gain = _unshaded_gain(opacity, shaded)
    assert torch.isfinite(gain).all()
    assert gain.tolist()[:4] == [1.0, 2.0, 1.0, 1.0]
    # The scaled colour of a ray (mean colour times opacity) never exceeds its opacity.
    assert float(1e-30 * gain[4]) <= 0.9 + 1e-6
