"""The headlight table (``representation.headlight``): one colour per angle between normal and view,
added to the decoded colour of every surface point."""

import math

import pytest
import torch
import torch.nn.functional as F

from visnerf.checkpoint import load_checkpoint
from visnerf.config import FieldConfig
from visnerf.representation.headlight import HeadlightTable
from visnerf.testing import make_tiny_checkpoint, make_tiny_field

AXES = [("time", [0.0, 1.0, 2.0])]


def blinn_phong(angle: torch.Tensor) -> torch.Tensor:
    """A headlight's highlight at the angle between normal and view: 0.3 cos^40 (white)."""
    return (0.3 * torch.cos(angle).clamp_min(0.0) ** 40)[:, None].expand(-1, 3)


def ramp(angle: torch.Tensor) -> torch.Tensor:
    return (0.8 - 0.4 * angle)[:, None] * torch.tensor([1.0, 0.5, -0.2])


def test_the_table_is_exact_at_its_knots_and_linear_between():
    table = HeadlightTable(91)
    knots = torch.linspace(0.0, math.pi, 91, dtype=torch.float64)
    with torch.no_grad():
        table.table.copy_(blinn_phong(knots).float())
    at_knots = table(torch.cos(knots)[:, None])
    assert torch.allclose(at_knots, blinn_phong(knots).float(), atol=1e-5)
    # Half-way between two knots: the mean of their values (the angle, not the cosine, is uniform).
    middle = (knots[:-1] + knots[1:]) / 2
    expected = (blinn_phong(knots[:-1]) + blinn_phong(knots[1:])).float() / 2
    assert torch.allclose(table(torch.cos(middle)[:, None]), expected, atol=1e-4)
    # Against the lobe itself: two-degree knots follow cos^40 to within 1 % of its height.
    angles = torch.rand(2000, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * math.pi
    assert float((table(torch.cos(angles)[:, None]).detach() - blinn_phong(angles).float()).abs().max()) < 0.01 * 0.3


def test_cosines_beyond_one_read_the_end_knots_and_take_no_gradient():
    table = HeadlightTable(5)
    with torch.no_grad():
        table.table.copy_(torch.arange(15.0).view(5, 3))
    cos = torch.tensor([[1.0 + 1e-6], [-1.0 - 1e-6], [1.0], [-1.0]], requires_grad=True)
    out = table(cos)
    assert torch.equal(out[0], table.table[0]) and torch.equal(out[1], table.table[4])
    assert torch.isfinite(out).all()
    out.sum().backward()
    assert cos.grad is None  # the shading reads the normal, it does not move the geometry
    assert table.table.grad is not None and torch.isfinite(table.table.grad).all()


def test_a_table_needs_two_knots():
    with pytest.raises(ValueError, match="at least 2"):
        HeadlightTable(1)
    with pytest.raises(ValueError, match="headlight_bins"):
        FieldConfig(headlight_bins=1)
    with pytest.raises(ValueError, match="headlight_bins"):
        FieldConfig(headlight_bins=-3)


def test_the_field_adds_the_table_at_its_normals_angle_and_stays_in_range():
    field, _ = make_tiny_field(AXES, seed=2, resolution=10, headlight_bins=91)
    plain, _ = make_tiny_field(AXES, seed=2, resolution=10, surface_normals=True)
    plain.load_state_dict({k: v for k, v in field.state_dict().items() if not k.startswith("headlight.")})
    g = torch.Generator().manual_seed(4)
    points = (torch.rand(300, 3, generator=g) - 0.5) * 0.8
    dirs = F.normalize(torch.randn(300, 3, generator=g), dim=-1)
    q_d, q_a = field.param_features(torch.full((300, 1), 0.4))
    with torch.no_grad():
        assert torch.equal(field.color(points, dirs, q_a, q_d), plain.color(points, dirs, q_a, q_d))  # zeros: no effect
        # linear in the angle, which linear interpolation between knots reproduces exactly
        field.headlight.table.copy_(ramp(torch.linspace(0.0, math.pi, 91)))
        lit = field.color(points, dirs, q_a, q_d)
        base = plain.color(points, dirs, q_a, q_d)
        angle = torch.acos(field.normal_cosines(points, dirs, q_d).clamp(-1, 1))[:, 0]
    assert torch.allclose(lit, (base + ramp(angle)).clamp(0, 1), atol=1e-5)
    assert float(lit.min()) >= 0.0 and float(lit.max()) <= 1.0 and float(lit.max()) == 1.0


def test_the_table_round_trips_through_a_checkpoint(tmp_path):
    path = make_tiny_checkpoint(tmp_path / "lit.safetensors", AXES, kind="ir", headlight_bins=31)
    field, meta = load_checkpoint(path, torch.device("cpu"))
    assert meta.field.headlight_bins == 31 and field.headlight is not None and field.headlight.bins == 31
    assert field.reads_normals
