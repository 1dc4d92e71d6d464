"""Facing cosines (``FieldConfig.facing_vectors``): the cosine of learnt per-point vectors with the
view direction, read by the colour decoder. Against closed forms, through the folded inference
path, through a checkpoint, and into the optimizer."""

import math

import pytest
import torch

from visnerf.checkpoint import load_checkpoint
from visnerf.config import FieldConfig, TrainConfig
from visnerf.representation.field import facing_cosines
from visnerf.representation.frame_field import FrameField
from visnerf.testing import make_tiny_checkpoint, make_tiny_field
from visnerf.training.step import make_optimizer


def test_facing_cosines_are_the_cosines_of_each_vector_with_the_direction() -> None:
    d = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]])
    vectors = torch.tensor([
        [0.0, 0.0, 5.0, 0.0, 2.0, 2.0, 0.0, 0.0, 0.0],  # along d, at 45 degrees, of length zero
        [3.0, 4.0, 0.0, -0.6, -0.8, 0.0, 1e-30, 0.0, 0.0],  # along d, opposite, tiny
    ])
    got = facing_cosines(vectors, d)
    want = torch.tensor([[1.0, math.sqrt(0.5), 0.0], [1.0, -1.0, 0.0]])
    assert got.shape == (2, 3) and torch.isfinite(got).all()
    torch.testing.assert_close(got, want, atol=1e-6, rtol=0)


def test_a_random_direction_set_matches_a_float64_reference() -> None:
    g = torch.Generator().manual_seed(4)
    vectors = torch.randn(300, 12, generator=g)
    d = torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=torch.float64), dim=-1)
    u = vectors.double().view(300, 4, 3)
    want = (u * d[:, None]).sum(-1) / u.norm(dim=-1)
    torch.testing.assert_close(facing_cosines(vectors, d.float()).double(), want, atol=1e-6, rtol=0)


@pytest.fixture()
def facing_field():
    field, _ = make_tiny_field([("a", [0.0, 0.5, 1.0])], seed=5, resolution=10, facing_vectors=3)
    with torch.no_grad():
        field.facing.weight.normal_(0.0, 1.0)
    return field.eval()


def test_the_colour_turns_with_the_view_through_the_facing_vectors(facing_field) -> None:
    points = torch.zeros(2, 3)
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    q_a = facing_field.param_features(torch.tensor([[0.2]]))[1].expand(2, -1)
    with torch.no_grad():
        with_facing = facing_field.color(points, d, q_a)
        facing_field.color_decoder.hidden.weight[:, -3:] = 0.0  # the decoder stops reading the cosines
        facing_field.color_decoder.hidden.weight[:, -19:-3] = 0.0  # and the harmonics
        without = facing_field.color(points, d, q_a)
    assert not torch.allclose(with_facing[0], with_facing[1])
    torch.testing.assert_close(without[0], without[1])


@pytest.mark.parametrize("param", [-1.0, 0.1, 1.0])
def test_the_folded_inference_colour_equals_the_field(facing_field, param: float) -> None:
    g = torch.Generator().manual_seed(1)
    points = torch.rand(400, 3, generator=g) - 0.5
    dirs = torch.nn.functional.normalize(torch.randn(400, 3, generator=g), dim=-1)
    q_d, q_a = facing_field.param_features(torch.tensor([[param]]))
    with torch.no_grad():
        want = facing_field.color(points, dirs, q_a.expand(400, -1))
        exact = FrameField(facing_field, q_d, q_a)
        torch.testing.assert_close(exact.color(points, exact.direction_terms(dirs)), want, atol=1e-6, rtol=0)
        rounded = FrameField(facing_field, q_d, q_a, torch.bfloat16)
        got = rounded.color(points, rounded.direction_terms(dirs))
    assert float((got - want).abs().max()) < 2e-2 and float((got - want).abs().mean()) < 3e-3


def test_facing_vectors_survive_a_checkpoint_and_older_checkpoints_have_none(tmp_path) -> None:
    old_field, old_meta = load_checkpoint(make_tiny_checkpoint(tmp_path / "plain.safetensors"), torch.device("cpu"))
    assert old_meta.field.facing_vectors == 0 and old_field.facing is None
    written = make_tiny_field([("a", [0.0, 1.0])], seed=0, facing_vectors=2)[0]
    field, meta = load_checkpoint(make_tiny_checkpoint(tmp_path / "f.safetensors", facing_vectors=2), torch.device("cpu"))
    assert meta.field.facing_vectors == 2
    torch.testing.assert_close(field.facing.weight, written.facing.weight, atol=0, rtol=0)
    saved = {k: v for k, v in meta.field.__dict__.items() if k != "facing_vectors"}  # as written before the option
    assert FieldConfig.from_dict(saved).facing_vectors == 0


def test_the_facing_map_is_trained_with_the_networks(facing_field) -> None:
    optimizer = make_optimizer(facing_field.train(), TrainConfig(), 1.0)
    networks = optimizer.param_groups[1]["params"]
    assert any(p is facing_field.facing.weight for p in networks)
    points = torch.rand(50, 3) - 0.5
    dirs = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    q_a = facing_field.param_features(torch.tensor([[0.3]]))[1].expand(50, -1)
    facing_field.color(points, dirs, q_a).sum().backward()
    assert facing_field.facing.weight.grad is not None and facing_field.facing.weight.grad.abs().sum() > 0


def test_a_negative_count_is_refused() -> None:
    with pytest.raises(ValueError, match="facing_vectors"):
        FieldConfig(facing_vectors=-1)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_every_colour_product_runs_on_padded_rows(facing_field, dtype, monkeypatch) -> None:
    """oneDNN builds and caches a kernel for every new row count of a bf16 product: each of the
    folded colour path's products, the facing map's included, takes one of ``padded_rows``'s
    counts whatever the number of samples (the facing map once took the count itself, and the
    cache grew a render server by 1.2 MB a frame). The colour is the one of the field still."""
    import visnerf.representation.frame_field as frame_field_module
    from visnerf.representation.decoders import padded_rows

    rows: list[int] = []
    linear = torch.nn.functional.linear

    def recording_linear(x, *args):
        rows.append(x.shape[0])
        return linear(x, *args)

    q_d, q_a = facing_field.param_features(torch.tensor([[0.4]]))
    g = torch.Generator().manual_seed(4)
    cases = []
    for n in (1, 37, 130, 1500):
        points = torch.rand(n, 3, generator=g) - 0.5
        dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
        with torch.no_grad():
            cases.append((points, dirs, facing_field.color(points, dirs, q_a.expand(n, -1))))
    frame = FrameField(facing_field, q_d, q_a, dtype)
    monkeypatch.setattr(frame_field_module.F, "linear", recording_linear)  # torch's own, from here on
    for points, dirs, want in cases:
        with torch.no_grad():
            got = frame.color(points, frame.direction_terms(dirs))
        torch.testing.assert_close(got, want, atol=2e-2 if dtype == torch.bfloat16 else 1e-5, rtol=0)
    # the facing map and the output layer each once a case; a bf16 output layer on the CPU is the
    # compiled one (``output_kernel``), which builds no oneDNN kernel
    products = 4 if frame._color_out_f32 is not None else 8
    assert len(rows) >= products and all(r == padded_rows(r) for r in rows), rows
