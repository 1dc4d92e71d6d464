"""Row-wise int8 codes of the VM planes (``factor_codec``) and int8 checkpoints."""

import dataclasses

import pytest
import torch
from safetensors.torch import load_file, safe_open, save_file

from visnerf.checkpoint import CheckpointError, load_checkpoint, read_checkpoint, save_checkpoint
from visnerf.factor_codec import CODE_MAX, decode_rows, encode_rows
from visnerf.testing import make_tiny_checkpoint, make_tiny_field


def test_codes_of_a_row_by_hand():
    """Scale = max |x| / 127; codes round to nearest (ties to even); the largest magnitude is
    +-127 exactly."""
    codes, scale = encode_rows(torch.tensor([[0.0, 1.0, -2.0, 0.5, 2.0 / 127 * 10.5]]))
    assert scale.shape == (1, 1) and float(scale) == pytest.approx(2.0 / 127, rel=1e-7)
    assert codes.dtype == torch.int8
    assert codes.tolist() == [[0, 64, -127, 32, 10]]  # 63.5 -> 64, 31.75 -> 32, 10.5 -> 10


def test_decoding_is_within_half_a_step_and_rows_are_independent():
    torch.manual_seed(0)
    values = torch.randn(3, 5, 40) * torch.logspace(-4, 2, 5)[None, :, None]  # rows of very different size
    values[1, 2, 7] = 1e4  # one spike
    codes, scale = encode_rows(values)
    assert scale.shape == (3, 5, 1)
    back = decode_rows(codes, scale)
    assert bool(((back - values).abs() <= 0.5 * scale * (1 + 1e-6)).all())
    assert int(codes.abs().amax(dim=-1).min()) == CODE_MAX  # every non-zero row uses the full range
    # The spike coarsens its own row only: every other row codes as it did without it.
    calm = values.clone()
    calm[1, 2, 7] = 0.0
    calm_codes, calm_scale = encode_rows(calm)
    others = torch.ones(3, 5, dtype=torch.bool)
    others[1, 2] = False
    assert torch.equal(codes[others], calm_codes[others]) and torch.equal(scale[others], calm_scale[others])


def test_zero_rows_and_exact_multiples_are_exact():
    step = 0.25
    values = torch.tensor([[0.0, 0.0, 0.0], [-127 * step, 3 * step, 127 * step]])
    codes, scale = encode_rows(values)
    assert float(scale[0]) == 0.0 and codes[0].tolist() == [0, 0, 0]
    assert torch.equal(decode_rows(codes, scale), values)


def test_non_finite_values_are_refused():
    with pytest.raises(ValueError, match="non-finite"):
        encode_rows(torch.tensor([[1.0, float("nan")]]))


def _int8_checkpoint(tmp_path, name="q.safetensors", resolution=16):
    field, _ = make_tiny_field([("a", [0.0, 1.0])], resolution=resolution)
    meta = read_checkpoint(make_tiny_checkpoint(tmp_path / "base.safetensors"))[0]
    field.cfg = dataclasses.replace(field.cfg, factor_storage="int8")
    return field, save_checkpoint(field, dataclasses.replace(meta, field=field.cfg), tmp_path / name)


def test_int8_checkpoint_loads_decoded_planes_half_lines_and_the_rest_unchanged(tmp_path):
    field, path = _int8_checkpoint(tmp_path)
    loaded, meta = load_checkpoint(path, torch.device("cpu"))
    assert meta.field.factor_storage == "int8"
    _, stored = read_checkpoint(path)
    for name, value in field.state_dict().items():
        got = loaded.state_dict()[name]
        assert got.dtype == value.dtype
        if ".planes." in name:
            assert stored[name].dtype == torch.int8 and stored[name + ".row_scale"].shape == (*value.shape[:-1], 1)
            assert torch.equal(got, decode_rows(*encode_rows(value)))
            assert not torch.equal(got, value)  # the rounding is real
        elif ".lines." in name:
            assert torch.equal(got, value.half().float())
        else:
            assert torch.equal(got, value)


def test_int8_planes_take_a_quarter_of_the_float32_bytes_plus_their_scales(tmp_path):
    field, path = _int8_checkpoint(tmp_path, resolution=24)
    half_field, _ = make_tiny_field([("a", [0.0, 1.0])], resolution=24)
    meta = read_checkpoint(make_tiny_checkpoint(tmp_path / "base2.safetensors"))[0]
    half_field.cfg = dataclasses.replace(half_field.cfg, factor_storage="float16")
    half = save_checkpoint(half_field, dataclasses.replace(meta, field=half_field.cfg), tmp_path / "h.safetensors")
    planes = [v for k, v in field.state_dict().items() if ".planes." in k]
    # float16 -> int8 saves a byte per plane value and adds a float32 scale per row.
    expected = sum(p.numel() for p in planes) - sum(4 * p.numel() // p.shape[-1] for p in planes)

    def data_bytes(p):
        return sum(t.numel() * t.element_size() for t in read_checkpoint(p)[1].values())

    assert data_bytes(half) - data_bytes(path) == expected
    assert path.stat().st_size < half.stat().st_size


def _tampered(path, tmp_path, edit):
    with safe_open(str(path), "pt") as fh:
        metadata = fh.metadata()
    tensors = load_file(str(path))
    edit(tensors)
    out = tmp_path / "bad.safetensors"
    save_file(tensors, str(out), metadata=metadata)
    return out


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: t.pop("density_grid.planes.1.row_scale"), "missing"),
        (lambda t: t["appearance_grid.planes.0.row_scale"].neg_().sub_(1.0), "negative scales"),
        (lambda t: t["appearance_grid.planes.2.row_scale"].fill_(float("inf")), "non-finite"),
        (lambda t: t.__setitem__("density_grid.planes.0.row_scale", torch.ones(4, 16)), "shape"),
        (lambda t: t.__setitem__("density_grid.planes.0", t["density_grid.planes.0"].half()), "dtype"),
        (lambda t: t.__setitem__("density_grid.lines.0.row_scale", torch.ones(4, 1)), "unexpected"),
    ],
)
def test_tampered_int8_checkpoints_are_rejected_with_the_problem_named(tmp_path, edit, message):
    _, path = _int8_checkpoint(tmp_path)
    bad = _tampered(path, tmp_path, edit)
    with pytest.raises(CheckpointError, match=message):
        load_checkpoint(bad, torch.device("cpu"))
