"""Closed-form and reference checks of the model's numerical routines."""

import math

import numpy as np
import pytest
import torch

from visnerf.checkpoint import CheckpointError, load_checkpoint, read_checkpoint
from visnerf.rendering.aabb import intersect_aabb
from visnerf.rendering.volume import render_transmittance_from_density, render_weight_from_density
from visnerf.representation.param_axes import ParamAxes, interpolate_knots
from visnerf.representation.vm import VMGrid
from visnerf.testing import make_tiny_checkpoint

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def test_piecewise_constant_compositing_is_exact():
    # sigma = [1, 2, 0.5], delta = [0.1, 0.2, 0.4]: tau = [0.1, 0.4, 0.2]
    # T = [1, e^-0.1, e^-0.5], alpha = 1 - e^-tau, T_final = e^-0.7
    sig = torch.tensor([[1.0, 2.0, 0.5]], dtype=torch.float64)
    dl = torch.tensor([[0.1, 0.2, 0.4]], dtype=torch.float64)
    w, t, a = render_weight_from_density(sig, dl)
    assert torch.allclose(t, torch.tensor([[1.0, math.exp(-0.1), math.exp(-0.5)]], dtype=torch.float64), atol=1e-12)
    assert abs(float(w.sum()) - (1 - math.exp(-0.7))) < 1e-6
    colors = torch.tensor([[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]], dtype=torch.float64)
    rgb = (w[..., None] * colors).sum(1)
    expected = [1 - math.exp(-0.1), math.exp(-0.1) * (1 - math.exp(-0.4)), math.exp(-0.5) * (1 - math.exp(-0.2))]
    assert np.allclose(rgb[0].numpy(), expected, atol=1e-6)


def test_constant_density_opacity_closed_form():
    sigma, length, n = 3.0, 0.7, 1000
    sig = torch.full((1, n), sigma, dtype=torch.float64)
    dl = torch.full((1, n), length / n, dtype=torch.float64)
    w, _, _ = render_weight_from_density(sig, dl)
    assert abs(float(w.sum()) - (1 - math.exp(-sigma * length))) < 1e-9


@pytest.mark.parametrize("sigma", [0.0, 1e4, 1e6])
def test_stiff_cases_are_finite_with_finite_gradients(sigma):
    sig = torch.full((2, 8), sigma, dtype=torch.float32, requires_grad=True)
    dl = torch.full((2, 8), 1.0)
    w, t, _ = render_weight_from_density(sig, dl)
    (w.sum() + t.sum()).backward()
    assert torch.isfinite(w).all() and torch.isfinite(sig.grad).all()
    assert float(w.sum(-1).max()) <= 1.0 + 1e-6


def test_single_opaque_sample_takes_everything():
    sig = torch.tensor([[0.0, 1e5, 0.0]])
    w, _, _ = render_weight_from_density(sig, torch.ones(1, 3))
    assert torch.allclose(w, torch.tensor([[0.0, 1.0, 0.0]]))


def test_transmittance_non_increasing():
    sig = torch.rand(16, 64) * 5
    t = render_transmittance_from_density(sig, torch.full((16, 64), 0.05))
    assert (t[:, 1:] <= t[:, :-1] + 1e-7).all()


def test_aabb_axis_parallel_rays_with_signed_zero():
    o = torch.tensor([[0.0, 0.0, -3.0], [0.0, 0.0, -3.0], [2.0, 0.0, -3.0], [1.0, 0.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [-0.0, -0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    tn, tf, hit = intersect_aabb(o, d, BOX)
    assert hit.tolist() == [True, True, False, True]  # the last grazes the face x = 1 exactly
    assert torch.allclose(tn[:2], torch.tensor([2.0, 2.0])) and torch.allclose(tf[:2], torch.tensor([4.0, 4.0]))
    assert torch.isfinite(tn).all() and torch.isfinite(tf).all()


def test_aabb_origin_inside_and_miss():
    o = torch.tensor([[0.0, 0.0, 0.0], [0.0, 5.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    tn, tf, hit = intersect_aabb(o, d, BOX)
    assert hit.tolist() == [True, False]
    assert float(tn[0]) == 0.0 and abs(float(tf[0]) - 1.0) < 1e-6


def test_param_interpolation_ends_and_between():
    table = torch.tensor([[1.0], [3.0], [7.0]])
    knots = torch.tensor([-1.0, 0.0, 1.0])
    x = torch.tensor([-1.0, -0.5, 0.0, 0.25, 1.0, 2.0])
    out = interpolate_knots(table, knots, x)[:, 0]
    assert torch.allclose(out, torch.tensor([1.0, 2.0, 3.0, 4.0, 7.0, 7.0]))


def test_param_axes_of_ones_leave_features_unchanged():
    axes = ParamAxes((3, 5), 4)
    assert torch.equal(axes.sample(torch.rand(10, 2) * 2 - 1), torch.ones(10, 4))


def test_rank_one_vm_equals_outer_product():
    grid = VMGrid(1, (4, 5, 6), 0.1)
    with torch.no_grad():
        for p in grid.planes:
            p.fill_(0.0)
        for line in grid.lines:
            line.fill_(0.0)
        grid.planes[0][0] = torch.arange(20.0).reshape(5, 4)  # XY plane: [y, x]
        grid.lines[0][0] = torch.arange(6.0)  # Z line
    # grid point (x=1, y=2, z=3) in [-1, 1] coordinates
    coords = torch.tensor([[2 * 1 / 3 - 1, 2 * 2 / 4 - 1, 2 * 3 / 5 - 1]])
    feat = grid.sample(coords)
    assert abs(float(feat[0, 0]) - (2 * 4 + 1) * 3.0) < 1e-4
    assert abs(float(grid._sample(coords)[0, 0]) - (2 * 4 + 1) * 3.0) < 1e-4


def test_table_lookup_equals_grid_sample_in_value_and_gradient():
    """``VMGrid.sample`` (row tables, embedding_bag) against its slow twin ``_sample`` (grid_sample,
    indexing), in float64: features and the gradient of every factor for random cotangents, at
    random points, grid nodes, faces and corners."""
    torch.manual_seed(0)
    grid = VMGrid(4, (5, 7, 6), 0.3).double()
    coords = torch.rand(400, 3, dtype=torch.float64) * 2 - 1
    coords[:6] = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [1.0, -1.0, 0.5], [0.5, 0.0, -0.2],
                               [-1.0, 1.0, 1.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    fast, slow = grid.sample(coords), grid._sample(coords)
    assert torch.allclose(fast, slow, atol=1e-12)
    cotangent = torch.randn_like(fast)
    g_fast = torch.autograd.grad(fast, list(grid.parameters()), cotangent)
    g_slow = torch.autograd.grad(slow, list(grid.parameters()), cotangent)
    for a, b in zip(g_fast, g_slow, strict=True):
        assert torch.allclose(a, b, atol=1e-12)


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
