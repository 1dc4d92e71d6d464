"""Shading normals (``representation.field.normal_terms``): the normalised negative gradient of the
density by central differences, and its cosine with the view direction, against closed forms."""

import math

import pytest
import torch

from visnerf.representation.field import NORMAL_TERMS, normal_terms
from visnerf.testing import make_tiny_field


def test_a_linear_density_has_the_closed_form_normal_everywhere() -> None:
    slope = torch.tensor([3.0, -4.0, 12.0], dtype=torch.float64)  # |slope| = 13
    g = torch.Generator().manual_seed(0)
    points = (torch.rand(50, 3, generator=g, dtype=torch.float64) - 0.5)
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=g, dtype=torch.float64), dim=-1)
    terms = normal_terms(lambda p: 7.0 + p @ slope, points, dirs, 0.01)
    expected = -slope / 13.0
    assert terms.shape == (50, NORMAL_TERMS)
    assert torch.allclose(terms[:, :3], expected.expand(50, 3), atol=1e-12)
    assert torch.allclose(terms[:, 3], dirs @ expected, atol=1e-12)


def test_a_ball_has_radial_normals_and_faces_a_camera_looking_at_it() -> None:
    """Density falling with the distance from the centre: the normal points out of the ball; a ray
    aimed at the centre meets it head on (cosine -1)."""
    points = torch.tensor([[0.3, 0.0, 0.0], [0.0, -0.2, 0.0], [0.1, 0.1, 0.1]], dtype=torch.float64)
    dirs = -torch.nn.functional.normalize(points, dim=-1)  # from outside towards the centre
    terms = normal_terms(lambda p: 100.0 * (0.5 - p.norm(dim=-1)), points, dirs, 1e-4)
    assert torch.allclose(terms[:, :3], torch.nn.functional.normalize(points, dim=-1), atol=1e-7)
    assert torch.allclose(terms[:, 3], torch.full((3,), -1.0, dtype=torch.float64), atol=1e-7)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_flat_density_gives_a_zero_normal_not_a_division_by_zero(dtype: torch.dtype) -> None:
    points = torch.zeros(4, 3, dtype=dtype)
    dirs = torch.tensor([[1.0, 0.0, 0.0]] * 4, dtype=dtype)
    flat = normal_terms(lambda p: torch.full((p.shape[0],), 5.0, dtype=dtype), points, dirs, 0.01)
    assert torch.equal(flat, torch.zeros(4, NORMAL_TERMS, dtype=dtype))
    tiny = normal_terms(lambda p: 1e-30 * p[:, 0].to(dtype), points, dirs, 0.01)  # a vanishing slope
    assert torch.isfinite(tiny).all()


def test_the_fields_normals_follow_its_density_and_carry_no_graph() -> None:
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=5, resolution=10, shading_normals=True)
    g = torch.Generator().manual_seed(1)
    points = torch.rand(30, 3, generator=g) - 0.5
    dirs = torch.nn.functional.normalize(torch.randn(30, 3, generator=g), dim=-1)
    q_d, _ = field.param_features(torch.tensor([[0.4]]))
    terms = field.shading_normals(points, dirs, q_d.expand(30, -1))
    assert not terms.requires_grad
    h = field.normal_spacing()
    # An independent slow reference: one point at a time, the six probes written out.
    for i in range(0, 30, 7):
        grad = []
        for axis in range(3):
            step = torch.zeros(3)
            step[axis] = h
            plus = field.density((points[i] + step)[None], q_d)
            minus = field.density((points[i] - step)[None], q_d)
            grad.append(float((plus - minus)[0].detach()) / (2 * h))
        reference = -torch.tensor(grad) / math.sqrt(sum(v * v for v in grad))
        assert torch.allclose(terms[i, :3], reference, atol=1e-5)
        assert float(terms[i, 3]) == pytest.approx(float(reference @ dirs[i]), abs=1e-5)


def test_a_field_with_shading_normals_refuses_a_colour_without_them() -> None:
    field, _ = make_tiny_field([], seed=5, shading_normals=True)
    with pytest.raises(ValueError, match="surface normals"):
        field.color(torch.zeros(2, 3), torch.tensor([[0.0, 0.0, 1.0]] * 2), torch.ones(2, 4))
