"""Checkpoints: exact round trips, factor storage, and every kind of tampered or foreign file refused."""

from pathlib import Path

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


def test_version_1_checkpoints_without_factor_storage_read_as_float32(tmp_path):
    from visnerf.testing import make_tiny_field

    field, _ = make_tiny_field([("a", [0.0, 1.0])])
    path = _save_with_storage(field, tmp_path / "old.safetensors", "float32")
    old = _tamper(path, tmp_path, lambda t, m: m.__setitem__("visnerf", m["visnerf"].replace(
        ', "factor_storage": "float32"', "").replace('"format_version": 2', '"format_version": 1')))
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
        (lambda t, m: m.__setitem__("visnerf", m["visnerf"].replace('"format_version": 2', '"format_version": 9')), "version"),
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


def _edit_document(edit):
    """A ``_tamper`` edit of the metadata document (NaN and infinities written as json writes them)."""
    import json

    def apply(tensors, metadata):
        document = json.loads(metadata["visnerf"])
        edit(document)
        metadata["visnerf"] = json.dumps(document)

    return apply


def _axis(i, **changes):
    return lambda d: d["param_axes"][i].update(changes)


def _set(**changes):
    return lambda d: d.update(changes)


def _in(section, **changes):
    return lambda d: d[section].update(changes)


METADATA_DEFECTS = [
    # no NaN or infinity anywhere, named where it is
    (_set(background=[1.0, float("nan"), 1.0]), "background[1] is NaN"),
    (_in("camera", distance=float("inf")), "camera.distance is Infinity"),
    (_in("provenance", val_psnr=float("-inf")), "provenance.val_psnr is -Infinity"),
    # the provenance record (``provenance.Provenance``)
    (_in("provenance", colour="red"), "provenance: unknown key(s) ['colour']"),
    (_in("provenance", iterations=-3), "provenance: iterations must be a whole number of at least 0"),
    (_in("provenance", val_psnr="high"), "provenance: val_psnr must be a finite number"),
    (_in("provenance", choices=[{"name": "x"}]), "provenance: choices[0] must have a name, a value and a reason"),
    (_axis(1, values=[0.0, float("nan")]), "param_axes[1].values[1] is NaN"),
    # parameter axes
    (_axis(0, default=1.5), "param_axes[0].default 1.5 is outside [0, 1]"),
    (_axis(0, default=-0.1), "param_axes[0].default -0.1 is outside [0, 1]"),
    (_axis(0, min=2.0), "param_axes[0].min 2.0 is above param_axes[0].max 1.0"),
    (_axis(0, min=1.0, values=[1.0, 1.0], default=1.0), "param_axes[0].min must be below param_axes[0].max"),
    (_axis(0, values=[1.0, 0.0]), "param_axes[0].values must increase strictly"),
    (_axis(0, values=[0.5, 0.5]), "param_axes[0].values must increase strictly"),
    (_axis(0, values=[0.0, 1.5]), "param_axes[0].values[1] 1.5 is outside [0, 1]"),
    (_axis(0, values=[]), "param_axes[0].values must list at least one training value"),
    (_axis(0, min="0"), "param_axes[0].min must be a number"),
    (_axis(0, default=True), "param_axes[0].default must be a number"),
    (_axis(1, name="a"), "param_axes[1].name 'a' names a second axis"),
    (_axis(0, name="azimuth"), "param_axes[0].name 'azimuth' is the name of a render request field"),
    (_axis(1, name="format"), "param_axes[1].name 'format' is the name of a render request field"),
    (_axis(0, name=""), "param_axes[0].name must be a name of 1 to 64 characters"),
    (_axis(0, name=" a"), "param_axes[0].name ' a' has control characters or surrounding spaces"),
    (lambda d: d["param_axes"][0].pop("default"), "param_axes[0].default is missing"),
    # the scene
    (_set(background=[1.0, 1.0, 1.5]), "background[2] 1.5 is outside [0, 1]"),
    (_set(background=[1.0, 1.0]), "background must hold 3 numbers, got 2"),
    (_set(background="white"), "background must be a list of numbers"),
    (_set(kind="hologram"), "kind must be one of dvr, ir, got 'hologram'"),
    (_set(image_width=0), "image_width must be a whole number in [1, 65536], got 0"),
    (_set(image_height=-64), "image_height must be a whole number in [1, 65536], got -64"),
    (_set(image_width=64.5), "image_width must be a whole number"),
    (lambda d: d.pop("image_height"), "image_height is missing"),
    (_in("camera", fov_deg=180.0), "camera.fov_deg 180.0 is outside (0, 180)"),
    (_in("camera", distance=0.0), "camera.distance 0.0 is outside (0, 1e+06)"),
    (_in("camera", elevation=95.0), "camera.elevation 95.0 is outside [-90, 90]"),
    (_in("camera", zoom=2.0), "camera.zoom is not a camera value"),
    (_set(bbox=[[0.5, -0.5, -0.5], [-0.5, 0.5, 0.5]]), "bbox[0][0] 0.5 is not below bbox[1][0] -0.5"),
    (_set(bbox=[[0, 0, 0]]), "bbox must be two corners"),
    (_set(title=7), "title must be a string"),
    (_set(occupancy_resolution=[8, 8, 0]), "occupancy_resolution[2] must be a whole number"),
    (_set(provenance=[]), "provenance must be a JSON object"),
    # the render configuration, bounded
    (_in("render", max_samples=1e9), "render: max_samples must be a whole number, got 1000000000.0"),
    (_in("render", max_samples=10**9), "render: max_samples must be a whole number in [1, 16384]"),
    (_in("render", max_samples=0), "render: max_samples must be a whole number of at least 1"),
    (_in("render", step_ratio=1e-9), "render: step_ratio must be a finite number in [0.01, 16]"),
    (_in("render", full_step_ratio=1e6), "render: full_step_ratio must be a finite number in [0.01, 16]"),
    (_in("render", preview_step_factor=100.0), "render: preview_step_factor must be a finite number in [0.01, 16]"),
    (_in("render", preview_scale=0.001), "render: preview_scale must be a finite number in [0.0625, 1]"),
    (_in("render", early_stop_eps=1.0), "render: early_stop_eps must be in [0, 1)"),
    (_in("render", bf16="yes"), "render: bf16 must be true or false"),
    # the field configuration
    (_in("field", hidden_width="16"), "field: hidden_width must be a whole number"),
    (_in("field", resolution=[8, 8, 10**6]), "field: resolution must be whole numbers in [2, 4096]"),
    (_in("field", pos_encoding_freqs=1000), "field: pos_encoding_freqs must be a whole number in [0, 32]"),
]


@pytest.mark.parametrize(("edit", "message"), METADATA_DEFECTS, ids=[m for _, m in METADATA_DEFECTS])
def test_metadata_defects_are_refused_naming_the_field(tmp_path, edit, message):
    good = make_tiny_checkpoint(tmp_path / "good.safetensors", [("a", [0.0, 1.0]), ("b", [0.0, 0.5, 1.0])])
    bad = _tamper(good, tmp_path, _edit_document(edit))
    with pytest.raises(CheckpointError) as refused:
        read_checkpoint(bad)
    assert message in str(refused.value)


def test_overflowing_numbers_in_the_text_are_refused(tmp_path):
    good = make_tiny_checkpoint(tmp_path / "good.safetensors")
    bad = _tamper(good, tmp_path, lambda t, m: m.__setitem__("visnerf", m["visnerf"].replace('"max": 1.0', '"max": 1e999')))
    with pytest.raises(CheckpointError, match=r"param_axes\[0\]\.max is 1e999: every number must be finite"):
        read_checkpoint(bad)


def test_the_bundled_checkpoints_pass_the_metadata_checks():
    """Their metadata only (the header), not their tensors."""
    import json
    import struct
    from pathlib import Path

    from visnerf.checkpoint import CheckpointMeta

    bundled = sorted((Path(__file__).resolve().parents[2] / "checkpoints").glob("*.safetensors"))
    assert bundled
    for path in bundled:
        with path.open("rb") as f:
            (n,) = struct.unpack("<Q", f.read(8))
            header = json.loads(f.read(n))
        meta = CheckpointMeta.from_json(header["__metadata__"]["visnerf"])
        assert meta.kind in ("dvr", "ir") and meta.param_axes, path.name


def test_a_current_checkpoint_naming_an_unknown_key_is_refused(tmp_path):
    """One rule for every configuration: a key it does not know is an error that names it (version
    1 documents are migrated first; the bundled checkpoints are version 1 and load)."""
    from visnerf.testing import make_tiny_field

    field, _ = make_tiny_field([("a", [0.0, 1.0])])
    path = _save_with_storage(field, tmp_path / "new.safetensors", "float32")
    bad = _tamper(path, tmp_path, lambda t, m: m.__setitem__("visnerf", m["visnerf"].replace(
        '"render": {', '"render": {"chunk_rays": 4096, ')))
    with pytest.raises(CheckpointError, match="render: unknown render configuration keys.*chunk_rays"):
        read_checkpoint(bad)
    for bundled in sorted((Path(__file__).resolve().parents[2] / "checkpoints").glob("*.safetensors")):
        meta, _ = read_checkpoint(bundled)
        assert meta.format_version == 2
