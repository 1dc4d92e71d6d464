"""The bake: grid helpers against pooling, the colour fit against a closed form, the field's
view logits against its colour, frames from a bake against closed forms and against the model."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from visnerf.bake import baking
from visnerf.bake.bake_render import DenseBake, render_bake
from visnerf.bake.baking import BakeTarget, bake_setting, choose_sh_degree, colour_basis, fibonacci_directions
from visnerf.bake.scene_bake import bake_scene
from visnerf.config.bake import BakeConfig
from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.inference import load_scene
from visnerf.representation.decoders import encode_sh
from visnerf.representation.frame_field import FrameField
from visnerf.testing import make_tiny_field

REPO = Path(__file__).resolve().parents[3]


def test_grid_helpers_equal_pooling() -> None:
    g = torch.Generator().manual_seed(0)
    cells = torch.rand(7, 5, 6, generator=g) > 0.8
    pooled = F.max_pool3d(cells[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
    assert torch.equal(baking._dilate(cells), pooled)
    pooled2 = F.max_pool3d(cells[None, None].float(), 5, stride=1, padding=2)[0, 0] > 0
    assert torch.equal(baking._dilate(cells, 2), pooled2)
    corners = F.max_pool3d(F.pad(cells[None, None].float(), (1,) * 6), 2, stride=1)[0, 0] > 0
    assert torch.equal(baking._cell_vertices(cells), corners)
    values = torch.rand(8, 6, 7, generator=g)
    assert torch.equal(baking._cell_max(values), F.max_pool3d(values[None, None], 2, stride=1)[0, 0])


def test_fibonacci_directions_are_unit_and_spread() -> None:
    d = fibonacci_directions(64)
    assert torch.allclose(d.norm(dim=-1), torch.ones(64), atol=1e-6)
    assert d.mean(0).abs().max() < 0.05


class LinearSource:
    """A field whose logits are exactly a degree-1 harmonic sum with known coefficients, over a
    slab of constant density: the fit must recover them and the frame must match closed forms."""

    def __init__(self, coefficients: torch.Tensor, sigma: float, shift: float = 0.0) -> None:
        self.coefficients = coefficients  # [4, 3]
        self.shift = shift
        self.sigma = sigma

    @property
    def density_activation(self) -> tuple[float, float]:
        return self.shift, 1.0

    @property
    def level_step(self) -> None:
        return None

    def raw_density(self, points: torch.Tensor) -> torch.Tensor:
        # softplus^-1(sigma) inside |z| < 0.25, far below zero outside
        inside = points[:, 2].abs() <= 0.25 + 1e-6  # the faces on vertices
        value = torch.where(inside, torch.tensor(math.log(math.expm1(self.sigma))), torch.tensor(-60.0))
        return value - self.shift

    def level_probes(self, points: torch.Tensor) -> torch.Tensor:
        raise AssertionError("no level axis")

    def view_logits(self, points, directions, probes=None) -> torch.Tensor:
        m, v = directions.shape[:2]
        basis = encode_sh(directions.reshape(-1, 3), 1).view(m, v, 4)
        return basis @ self.coefficients


def _target(union=None) -> BakeTarget:
    return BakeTarget(aabb=((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5)), model_grid=(17, 17, 17), step=0.01,
                      occupancy_threshold=1e-4, early_stop_eps=1e-4, union=union, cosine_powers=(),
                      background=(1.0, 1.0, 1.0), kind="dvr", title="slab", params={}, source={})


def test_the_fit_recovers_a_harmonic_colour_and_picks_its_degree() -> None:
    coefficients = torch.tensor([[0.5, -1.0, 0.2], [0.8, 0.0, -0.3], [0.0, 0.4, 0.1], [-0.6, 0.2, 0.0]])
    source = LinearSource(coefficients, 3.0)
    points = torch.rand(50, 3) - 0.5
    coef, error = baking._fit_colours(source, points, "sh", 1, (), BakeConfig())
    assert error < 0.05
    assert torch.allclose(coef.view(50, 4, 3), coefficients.expand(50, 4, 3), atol=2e-3)  # the ridge's bias only
    degree, reason = choose_sh_degree(source, points, "sh", (), BakeConfig())
    assert degree == 1 and "degree 0:" in reason
    flat = LinearSource(coefficients * torch.tensor([[1.0], [0.0], [0.0], [0.0]]), 3.0)
    assert choose_sh_degree(flat, points, "sh", (), BakeConfig())[0] == 0


@pytest.mark.parametrize("shift", [0.0, 150.0, -150.0])
def test_a_frame_of_a_baked_slab_equals_its_closed_form(shift) -> None:
    """A slab |z| < 0.25 of density 3 seen head on: opacity 1 - exp(-3 * 0.5) over a white
    background, colour the sigmoid of the harmonic sum at the view direction. The field's shift
    (a level's, far from zero) is baked into the raw density: the fill of unstored vertices never
    meets it."""
    coefficients = torch.tensor([[1.0, -1.0, 0.0], [0.0, 0.0, 0.0], [0.5, 0.2, -0.4], [0.0, 0.0, 0.0]])
    bake = bake_setting(LinearSource(coefficients, 3.0, shift), _target(), BakeConfig(max_sh_degree=1))
    c2w = torch.tensor(orbit_c2w(0.0, 0.0, 3.0), dtype=torch.float32)  # on +z looking down -z
    image = render_bake(DenseBake.of(bake), c2w, Intrinsics.from_view_height(8, 8, 0.5))
    d = torch.tensor([[0.0, 0.0, -1.0]])
    colour = torch.sigmoid(encode_sh(d, 1) @ coefficients)[0]
    alpha = 1.0 - math.exp(-3.0 * 0.5)
    expected = (colour * alpha + (1.0 - alpha)).numpy() * 255.0
    # the slab's faces fall between samples: half a step of density each side at most
    slack = 255.0 * 3.0 * 0.01 + 1.0
    assert np.abs(image.astype(np.float64) - expected).max() <= slack


def test_the_union_grid_bounds_the_bake() -> None:
    union = torch.zeros(8, 8, 8, dtype=torch.bool)
    union[:, :4] = True  # the half y < 0
    bake = bake_setting(LinearSource(torch.zeros(4, 3), 3.0), _target(union), BakeConfig())
    occ = bake.dense_occupancy()  # [z, y, x]
    assert occ[:, 10:].sum() == 0 and occ[:, :6].sum() > 0


@pytest.fixture(params=[-1, 0], ids=["volume", "level"])
def frame_field(request) -> FrameField:
    f, _ = make_tiny_field([("a", [0.0, 0.5, 1.0]), ("b", [0.0, 1.0])], seed=3, resolution=12,
                           level_set_axis=request.param, facing_vectors=2 if request.param < 0 else 0,
                           level_cosine_powers=(4, 16))
    f = f.eval()
    qd, qa = f.param_features(torch.tensor([[0.3, 0.6]]))
    return FrameField(f, qd, qa, torch.float32)


def test_view_logits_are_the_colour_before_its_sigmoid(frame_field) -> None:
    g = torch.Generator().manual_seed(1)
    points = torch.rand(40, 3, generator=g) - 0.5
    dirs = F.normalize(torch.randn(40, 5, 3, generator=g), dim=-1)
    logits = frame_field.view_logits(points, dirs)
    for j in range(5):
        colour = frame_field.color(points, frame_field.direction_terms(dirs[:, j]))
        assert torch.allclose(torch.sigmoid(logits[:, j]), colour, atol=1e-5)
    raw = frame_field.raw_density(points)
    shift, scale = frame_field.density_activation
    assert torch.allclose(F.softplus(raw + shift) * scale, frame_field.density(points), atol=1e-5)


def test_level_shading_reads_the_normal_of_the_probes() -> None:
    probes = torch.tensor([[1.0, 1.0, -1.0, -1.0]])  # gradient along +x
    basis = colour_basis("level", 0, torch.tensor([[1.0, 0.0, 0.0]]), probes, (4,))
    assert torch.allclose(basis, torch.tensor([[0.28209479, 1.0, 1.0]]))


@pytest.mark.parametrize(("name", "floor"), [("vortex_tf1", 38.0), ("tangle_iso", 30.0)])
def test_frames_from_a_bundled_bake_match_the_model(name, floor) -> None:
    scene = load_scene(REPO / "checkpoints" / f"{name}.safetensors")
    bake = bake_scene(scene)
    cam = scene.info.camera
    c2w = orbit_c2w(40.0, 25.0, cam["distance"])
    ref = scene.render(c2w, cam["fov_deg"], 96, 96, {}, "full").astype(np.float64)
    img = render_bake(DenseBake.of(bake), torch.tensor(c2w, dtype=torch.float32),
                      Intrinsics.from_fov(96, 96, math.radians(cam["fov_deg"]))).astype(np.float64)
    psnr = 10 * math.log10(255.0**2 / max(((img - ref) ** 2).mean(), 1e-12))
    assert psnr >= floor, psnr
