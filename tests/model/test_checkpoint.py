"""Checkpoints: exact round trips, factor storage, and every kind of tampered or foreign file refused."""

import pytest
import torch

from visnerf.checkpoint import CheckpointError, load_checkpoint, read_checkpoint
from visnerf.testing import make_tiny_checkpoint


def test_checkpoint_round_trip_is_exact(tmp_path):
    path = make_tiny_checkpoint(tmp_path / "a.safetensors", [("t", [0.0, 0.5, 1.0])])
    field, meta = load_checkpoint(path, torch.device("cpu"))
    meta2, tensors = read_checkpoint(path)
    for name, tensor in field.state_dict().items():
        assert torch.equal(tensor, tensors[name])
    assert meta2 == meta


def _save_with_storage(field, path, storage):
    import dataclasses

    from visnerf.checkpoint import save_checkpoint

    meta = read_checkpoint(make_tiny_checkpoint(path.with_suffix(".base.safetensors")))[0]
    field.cfg = dataclasses.replace(field.cfg, factor_storage=storage)
    return save_checkpoint(field, dataclasses.replace(meta, field=field.cfg), path)


def test_half_precision_factors_round_trip_and_halve_the_file(tmp_path):
    """Factors stored as float16 load back as exactly the float16-rounded values of the field
    (in float32, the field's dtype); everything else is stored unchanged."""
    from visnerf.testing import make_tiny_field

    field, _ = make_tiny_field([("a", [0.0, 1.0])], resolution=16)
    full = _save_with_storage(field, tmp_path / "f32.safetensors", "float32")
    half = _save_with_storage(field, tmp_path / "f16.safetensors", "float16")
    loaded, meta = load_checkpoint(half, torch.device("cpu"))
    assert meta.field.factor_storage == "float16"
    for name, value in field.state_dict().items():
        got = loaded.state_dict()[name]
        assert got.dtype == value.dtype
        if name.startswith(("density_grid.", "appearance_grid.")):
            assert torch.equal(got, value.half().float())
            assert not torch.equal(got, value)  # the rounding is real
        else:
            assert torch.equal(got, value)
    factor_bytes = sum(v.numel() * 2 for k, v in field.state_dict().items() if "_grid." in k)
    saved = full.stat().st_size - half.stat().st_size
    assert abs(saved - factor_bytes) <= 64  # the header's offsets are shorter too


def test_checkpoints_from_before_factor_storage_read_as_float32(tmp_path):
    from visnerf.testing import make_tiny_field

    field, _ = make_tiny_field([("a", [0.0, 1.0])])
    path = _save_with_storage(field, tmp_path / "old.safetensors", "float32")
    old = _tamper(path, tmp_path, lambda t, m: m.__setitem__("visnerf", m["visnerf"].replace(
        ', "factor_storage": "float32"', "")))
    from safetensors.torch import safe_open

    with safe_open(str(old), "pt") as fh:
        assert "factor_storage" not in fh.metadata()["visnerf"]
    meta, tensors = read_checkpoint(old)
    assert meta.field.factor_storage == "float32"
    assert tensors["density_grid.planes.0"].dtype == torch.float32


def test_factors_outside_half_precision_are_refused(tmp_path):
    from visnerf.testing import make_tiny_field

    field, _ = make_tiny_field([("a", [0.0, 1.0])])
    with torch.no_grad():
        field.appearance_grid.planes[1][0, 0, 0] = 1e5  # beyond float16's 65504
    target = tmp_path / "big.safetensors"
    with pytest.raises(CheckpointError, match="appearance_grid.planes.1.*cannot hold"):
        _save_with_storage(field, target, "float16")
    assert not target.exists()


def _swap_factor_storage(meta_json: str) -> str:
    """The metadata claiming the other factor dtype than the file holds."""
    f16, f32 = '"factor_storage": "float16"', '"factor_storage": "float32"'
    assert (f16 in meta_json) != (f32 in meta_json)
    return meta_json.replace(f16, f32) if f16 in meta_json else meta_json.replace(f32, f16)


def _tamper(path, tmp_path, edit):
    from safetensors.torch import load_file, safe_open, save_file

    with safe_open(str(path), "pt") as fh:
        metadata = fh.metadata()
    tensors = load_file(str(path))
    edit(tensors, metadata)
    out = tmp_path / "bad.safetensors"
    save_file(tensors, str(out), metadata=metadata)
    return out


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t, m: t.pop("density_decoder.out.bias"), "missing"),
        (lambda t, m: t.__setitem__("extra", torch.zeros(1)), "unexpected"),
        (lambda t, m: t.__setitem__("density_decoder.out.bias", torch.zeros(2)), "shape"),
        (lambda t, m: t["density_decoder.out.bias"].fill_(float("nan")), "non-finite"),
        (lambda t, m: t.__setitem__("density_grid.planes.0", t["density_grid.planes.0"].double()), "dtype"),
        (lambda t, m: m.__setitem__("visnerf", _swap_factor_storage(m["visnerf"])), "dtype"),
        (lambda t, m: m.__setitem__("visnerf", m["visnerf"].replace('"factor_storage": "float', '"factor_storage": "int')),
         "factor_storage"),
        (lambda t, m: m.__setitem__("visnerf", m["visnerf"].replace('"format_version": 1', '"format_version": 9')), "version"),
    ],
)
def test_tampered_checkpoints_are_rejected(tmp_path, edit, message):
    good = make_tiny_checkpoint(tmp_path / "good.safetensors")
    bad = _tamper(good, tmp_path, edit)
    with pytest.raises(CheckpointError, match=message):
        read_checkpoint(bad)


def test_pickle_and_truncated_files_are_rejected(tmp_path):
    good = make_tiny_checkpoint(tmp_path / "good.safetensors")
    pickled = tmp_path / "p.safetensors"
    torch.save({"x": torch.zeros(2)}, pickled)
    with pytest.raises(CheckpointError, match="not a safetensors"):
        read_checkpoint(pickled)
    truncated = tmp_path / "t.safetensors"
    truncated.write_bytes(good.read_bytes()[:-100])
    with pytest.raises(CheckpointError):
        read_checkpoint(truncated)
