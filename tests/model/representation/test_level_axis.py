"""A level axis (``FieldConfig.level_axis``): the density is one field whose logit the axis shifts.

Closed forms: the offsets interpolate linearly between their knots; the density at a value equals
``softplus(logit - offset(value)) * scale`` with ``logit`` the density's logit at an offset of 0;
the axis's CP vectors do not reach the density. The inference twin (``FrameField``) and a
checkpoint round trip hold the same field.
"""

import math

import pytest
import torch
import torch.nn.functional as F

from visnerf.checkpoint import CheckpointMeta, ParamAxis, load_checkpoint, save_checkpoint
from visnerf.config import FieldConfig, RenderConfig
from visnerf.representation.field import VisNerfField
from visnerf.representation.frame_field import FrameField
from visnerf.representation.param_axes import LevelOffsets

BOX = torch.tensor([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])
KNOTS = torch.tensor([-1.0, -0.2, 1.0])


def level_field(level_axis: int = 0, param_lengths: tuple[int, ...] = (3,), scale: float = 40.0) -> VisNerfField:
    torch.manual_seed(0)
    cfg = FieldConfig(resolution=(10, 10, 10), param_lengths=param_lengths, level_axis=level_axis,
                      density_scale=scale, density_shift=-1.0, init_scale=0.5, hidden_width=32)
    field = VisNerfField(cfg, BOX)
    field.set_param_knots([KNOTS] + [torch.linspace(-1, 1, n) for n in param_lengths[1:]])
    with torch.no_grad():
        field.density_level.table.copy_(torch.tensor([[0.5], [-1.5], [2.0]]) / LevelOffsets.GAIN)
        for table in (*field.density_params.tables, *field.appearance_params.tables):
            table.copy_(1.0 + 0.5 * torch.randn_like(table))
    return field.eval()


def inverse_softplus(y: torch.Tensor) -> torch.Tensor:
    return torch.log(torch.expm1(y))


def test_offsets_interpolate_linearly_between_knots_and_clamp_outside() -> None:
    offsets = LevelOffsets(3)
    offsets.set_knots(KNOTS)
    with torch.no_grad():
        offsets.table.copy_(torch.tensor([[0.0], [4.0], [-2.0]]))
    x = torch.tensor([-1.0, -0.6, -0.2, 0.4, 1.0, -3.0, 2.0])
    expected = torch.tensor([0.0, 2.0, 4.0, 1.0, -2.0, 0.0, -2.0]) * LevelOffsets.GAIN  # in logits
    assert torch.allclose(offsets.sample(x)[:, 0], expected, atol=1e-5)
    with pytest.raises(ValueError, match="strictly increasing"):
        offsets.set_knots(torch.tensor([0.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="3 values, got 2"):
        offsets.set_knots(torch.tensor([0.0, 1.0]))


@pytest.mark.parametrize("value", [-1.0, -0.6, -0.2, 0.3, 1.0])
def test_the_density_is_one_logit_shifted_by_the_offset(value: float) -> None:
    field = level_field()
    points = torch.rand(300, 3) - 0.5
    offset = float(field.density_level.sample(torch.tensor([value]))[0, 0].detach())
    with torch.no_grad():
        q_d, _ = field.param_features(torch.full((300, 1), value))
        sigma = field.density(points, q_d)
        field.density_level.table.zero_()
        q_0, _ = field.param_features(torch.full((300, 1), value))
        logit = inverse_softplus(field.density(points, q_0).double() / field.cfg.density_scale)
    expected = F.softplus(logit - offset) * field.cfg.density_scale
    assert torch.allclose(sigma.double(), expected, rtol=1e-4, atol=1e-6)


def test_the_level_axis_does_not_modulate_the_density_but_other_axes_do() -> None:
    field = level_field(param_lengths=(3, 2))
    points = torch.rand(200, 3) - 0.5
    params = torch.tensor([[0.1, -1.0]]).expand(200, 2)
    with torch.no_grad():
        before = field.density(points, field.param_features(params)[0])
        field.density_params.tables[0].mul_(3.0)  # the level axis's CP vectors: unused by the density
        assert torch.equal(field.density(points, field.param_features(params)[0]), before)
        field.density_params.tables[1].mul_(3.0)  # another axis: it modulates as before
        assert not torch.allclose(field.density(points, field.param_features(params)[0]), before)


def test_the_inference_twin_holds_the_same_level_field() -> None:
    field = level_field()
    points = torch.rand(400, 3) - 0.5
    dirs = F.normalize(torch.randn(400, 3), dim=-1)
    for value in (-1.0, -0.55, 0.7):
        q_d, q_a = field.param_features(torch.tensor([[value]]))
        frame = FrameField(field, q_d, q_a, torch.float32)
        with torch.no_grad():
            assert torch.allclose(frame.density(points), field.density(points, q_d.expand(400, -1)),
                                  rtol=1e-5, atol=1e-5)
            assert torch.allclose(frame.color(points, frame.direction_terms(dirs)),
                                  field.color(points, dirs, q_a.expand(400, -1)), atol=1e-6)


def test_a_level_field_survives_a_checkpoint_round_trip(tmp_path) -> None:
    field = level_field()
    axis = ParamAxis("isovalue", 0.25, 0.85, (0.25, 0.49, 0.85), 0.49)
    meta = CheckpointMeta(field=field.current_config(), render=RenderConfig(), param_axes=(axis,),
                          bbox=((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5)), image_width=32, image_height=32)
    path = save_checkpoint(field, meta, tmp_path / "level.safetensors")
    loaded, meta2 = load_checkpoint(path, torch.device("cpu"))
    assert meta2.field.level_axis == 0
    assert torch.equal(loaded.density_level.table, field.density_level.table)
    assert torch.equal(loaded.density_level.knots, KNOTS)


def test_a_level_axis_must_name_an_axis() -> None:
    with pytest.raises(ValueError, match="level_axis must be -1"):
        FieldConfig(param_lengths=(3,), level_axis=1)
    with pytest.raises(ValueError, match="names no parameter axis"):
        VisNerfField(FieldConfig(resolution=(4, 4, 4), level_axis=0), BOX)
    assert math.isfinite(float(level_field().density_level.table.sum()))
