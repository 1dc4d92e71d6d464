"""A field with a level axis (``FieldConfig.level_set_axis``): the density is one field minus a
level of the isovalue, so the surfaces of every value are nested level sets of it."""

import dataclasses

import pytest
import torch
import torch.nn.functional as F

from visnerf.config import FieldConfig
from visnerf.representation.field import VisNerfField
from visnerf.testing import make_tiny_field

AXES = [("iso", [0.1, 0.3, 0.4, 0.8]), ("time", [0.0, 1.0, 2.0])]


@pytest.fixture()
def field():
    f, _ = make_tiny_field(AXES, seed=5, resolution=10, level_set_axis=0)
    return f.eval()


def test_the_level_axis_has_no_density_factors_and_keeps_its_appearance_factors(field):
    assert len(field.density_params.tables) == 1 and field.density_params.tables[0].shape[0] == 3
    assert [t.shape[0] for t in field.appearance_params.tables] == [4, 3]
    assert field.levels is not None and field.levels.table.shape == (4, 1)


def test_density_is_the_shared_field_shifted_by_the_level(field):
    g = torch.Generator().manual_seed(0)
    points = torch.rand(300, 3, generator=g) - 0.5
    params = torch.tensor([[0.37, -0.2]]).expand(300, 2)
    q_d, _ = field.param_features(params)
    level = field.levels.sample(params[:, 0])
    assert torch.allclose(q_d[:, -1], level)
    with torch.no_grad():
        field.levels.log_sharpness.fill_(0.7)  # the sharpness multiplies g - level
        factors, got_level = field.split_density_features(q_d)
        flat = torch.cat([factors, torch.zeros_like(level)[:, None]], dim=1)  # the same field at level 0
        cfg = field.cfg
        inverse = torch.log(torch.expm1(field.density(points, flat) / cfg.density_scale))  # s g + shift
        expected = F.softplus(inverse - torch.exp(torch.tensor(0.7)) * level) * cfg.density_scale
        assert torch.allclose(field.density(points, q_d), expected, rtol=1e-4, atol=1e-6)
        assert torch.equal(got_level, level)


def test_surfaces_are_nested_along_the_level_axis(field):
    """Increasing levels: at every point the density falls (or holds) as the isovalue grows, so
    each value's inside contains the next one's, and values between knots lie between."""
    g = torch.Generator().manual_seed(1)
    points = torch.rand(500, 3, generator=g) - 0.5
    values = torch.linspace(-1.0, 1.0, 41)
    with torch.no_grad():
        sigma = torch.stack([field.density(points, field.param_features(torch.tensor([[v, 0.3]]).expand(500, 2))[0])
                             for v in values])  # [41, 500]
    assert bool((sigma[1:] <= sigma[:-1] * (1 + 1e-5) + 1e-7).all())
    assert float((sigma[0] - sigma[-1]).abs().max()) > 0.0


def test_the_level_axis_must_name_a_parameter_axis():
    with pytest.raises(ValueError, match="level_set_axis"):
        FieldConfig(param_lengths=(3,), level_set_axis=1)
    with pytest.raises(ValueError, match="level_set_axis"):
        FieldConfig(level_set_axis=-2)
    cfg = dataclasses.replace(FieldConfig(resolution=(8, 8, 8), level_set_axis=0), param_lengths=())
    with pytest.raises(ValueError, match="names no parameter axis"):
        VisNerfField(cfg, torch.tensor([[-0.5] * 3, [0.5] * 3]))


def test_a_checkpoint_keeps_its_levels(tmp_path):
    from visnerf.checkpoint import load_checkpoint
    from visnerf.testing import make_tiny_checkpoint

    path = make_tiny_checkpoint(tmp_path / "level.safetensors", AXES, kind="ir", level_set_axis=0)
    f, _ = load_checkpoint(path, torch.device("cpu"))
    assert f.cfg.level_set_axis == 0 and f.levels is not None
    assert torch.equal(f.levels.table.detach()[:, 0], torch.linspace(-1.0, 1.0, 4))


def test_level_cosines_of_a_linear_field_are_its_normal_against_the_view():
    from visnerf.representation.field import level_cosines, probe_points

    c = torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64)
    g = torch.Generator().manual_seed(2)
    points = torch.rand(50, 3, generator=g, dtype=torch.float64)
    dirs = F.normalize(torch.randn(50, 3, generator=g, dtype=torch.float64), dim=-1)
    raw = (probe_points(points, 0.01) @ c).view(-1, 4)  # g = c . x: four probes a point
    expected = (dirs @ c / c.norm()).float()[:, None]
    assert torch.allclose(level_cosines(raw, dirs), expected, atol=1e-6)
    assert torch.equal(level_cosines(torch.zeros(4, 4), dirs[:4].float()), torch.zeros(4, 1))  # flat g: 0
    # Second order: a quadratic g = |x|^2 / 2 has the gradient x exactly at any probe distance.
    quad = (probe_points(points, 0.3).pow(2).sum(-1) / 2).view(-1, 4)
    assert torch.allclose(level_cosines(quad, dirs), ((points * dirs).sum(-1) / points.norm(dim=-1)).float()[:, None],
                          atol=1e-5)
    # Powers of the facing part follow the cosine: zero where the surface faces away.
    with_powers = level_cosines(raw, dirs, (4, 64))
    assert with_powers.shape == (50, 3) and torch.equal(with_powers[:, :1], level_cosines(raw, dirs))
    facing = expected.clamp_min(0.0)
    assert torch.allclose(with_powers[:, 1:], torch.cat([facing.pow(4), facing.pow(64)], dim=1), atol=64e-6)  # k times
    assert bool((with_powers[expected[:, 0] < 0, 1:] == 0).all())


def test_level_normal_cosines_follow_the_derivative_of_the_level_field():
    """Against the derivative of ``g`` taken independently: a float64 copy of the field, central
    differences a millionth of a world unit apart, one axis at a time (the field's own probes are
    float32, here a thousandth of a voxel apart). The field is drawn as before the cosine's powers
    (the decoder's width changes the draw); the powers are then asked of the same field."""
    import copy

    field, _ = make_tiny_field(AXES, seed=5, resolution=10, level_set_axis=0, level_cosine_powers=())

    g = torch.Generator().manual_seed(3)
    points = (torch.rand(64, 3, generator=g) - 0.5) * 0.8
    dirs = F.normalize(torch.randn(64, 3, generator=g), dim=-1)
    params = torch.tensor([[0.1, 0.5]]).expand(64, 2)
    exact = copy.deepcopy(field).double()
    q = exact.param_features(params.double())[0][:, :-1]

    def g_at(x):
        coords = exact.to_grid(x)
        return exact.raw_density(coords, exact.density_grid.sample(coords), q)

    with torch.no_grad():
        p64, h = points.double(), 1e-6
        grad = torch.stack([(g_at(p64 + h * e) - g_at(p64 - h * e)) / (2 * h) for e in torch.eye(3, dtype=torch.float64)], 1)
    expected = ((grad * dirs.double()).sum(-1, keepdim=True) / grad.norm(dim=-1, keepdim=True)).float()
    fine = copy.deepcopy(field)
    powers = FieldConfig().level_cosine_powers
    fine.cfg = dataclasses.replace(field.cfg, level_normal_step=1e-3, level_cosine_powers=powers)
    got = fine.level_normal_cosines(points, dirs, field.param_features(params)[0])
    assert got.shape == (64, 1 + len(powers)) and len(powers) > 0
    assert torch.allclose(got[:, :1], expected, atol=2e-2)
    assert float((got[:, :1] - expected).abs().median()) < 2e-3
    # then each power of the facing part: d(c^k) = k c^(k-1) dc, so its error is at most k times the cosine's
    facing = expected.clamp(0.0, 1.0)
    for column, k in enumerate(powers, start=1):
        assert torch.allclose(got[:, column:column + 1], facing.pow(k), atol=k * 2e-2)
        assert bool((got[:, column] >= 0).all() and (got[:, column] <= 1).all())


def test_colour_of_a_level_axis_field_needs_its_density_features(field):
    points, dirs = torch.zeros(3, 3), F.normalize(torch.ones(3, 3), dim=-1)
    q_d, q_a = field.param_features(torch.zeros(3, 2))
    with pytest.raises(ValueError, match="density features"):
        field.color(points, dirs, q_a)
    assert field.color(points, dirs, q_a, q_d).shape == (3, 3)
