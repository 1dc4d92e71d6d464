"""The inference path (folded decoders, channels-last VM lookups, bf16 products, segment marching) against the
training path, which evaluates the field sample by sample with no shortcuts."""

import math
from dataclasses import replace

import pytest
import torch

from visnerf.config import RenderConfig
from visnerf.data.cameras import Intrinsics, image_rays, orbit_c2w
from visnerf.rendering.render_settings import RenderSettings
from visnerf.rendering.renderer import render_image
from visnerf.rendering.training_render import render_rays
from visnerf.representation import vm_kernel
from visnerf.representation.frame_field import FrameField, ModeTables
from visnerf.testing import make_tiny_field


@pytest.fixture(params=[-1, 0], ids=["factors", "level-axis"])
def field(request):
    """Parameter factors on both axes, or axis ``a`` a level axis (``param_axes.LevelAxis``)."""
    f, _ = make_tiny_field([("a", [0.0, 0.5, 1.0]), ("b", [0.0, 1.0])], seed=3, resolution=12,
                           level_set_axis=request.param)
    return f.eval()


def test_table_lookups_equal_the_concatenated_features(field) -> None:
    g = torch.Generator().manual_seed(0)
    coords = torch.rand(500, 3, generator=g) * 2 - 1
    coords[:6] = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [1.0, -1.0, 0.0],
                               [-1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1.0, 1.0, -1.0]])  # nodes and corners
    for grid in (field.appearance_grid, field.density_grid):
        expected = grid.sample(coords)  # [n, 3c]
        assert torch.allclose(ModeTables.of(grid).features(coords, torch.float32), expected, atol=1e-5)
        # Outside the box the tables read the border (inference never samples there).
        outside = coords * 1.3
        clamped = grid.sample(outside.clamp(-1.0, 1.0))
        assert torch.allclose(ModeTables.of(grid).features(outside, torch.float32), clamped, atol=1e-5)


def test_bf16_table_lookups_stay_within_bf16_rounding_of_float32(field) -> None:
    g = torch.Generator().manual_seed(2)
    coords = torch.rand(2000, 3, generator=g) * 2 - 1
    for grid in (field.appearance_grid, field.density_grid):
        expected = grid.sample(coords).detach()  # [n, 3c], float32
        got = ModeTables.of(grid, torch.bfloat16).features(coords, torch.bfloat16)
        assert got.dtype == torch.bfloat16
        # Factors, interpolation weights, both lookups and their product each round to 8 bits of
        # mantissa (2^-9 relative): a few such roundings, relative to the features' scale.
        err = (got.float() - expected).abs()
        scale = expected.abs().amax(dim=0, keepdim=True)  # [1, 3c]
        assert float((err / scale).max()) < 0.02  # measured 0.011
        assert float((err / scale).median()) < 1e-3  # measured 1.8e-4
        tables = ModeTables.of(grid, torch.bfloat16)
        assert tables.plane_table.dtype == tables.line_table.dtype == torch.bfloat16


def test_table_lookups_reject_a_grid_with_a_single_node() -> None:
    from visnerf.representation.vm import VMGrid

    with pytest.raises(ValueError, match="fewer than 2 nodes"):
        ModeTables.of(VMGrid(4, (8, 1, 8), 0.1))


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "torch"])
@pytest.mark.parametrize("params", [(-1.0, -1.0), (0.3, -0.2), (1.0, 1.0)])
def test_folded_decoders_equal_the_field(field, params, compiled) -> None:
    g = torch.Generator().manual_seed(1)
    points = torch.rand(400, 3, generator=g) - 0.5
    dirs = torch.nn.functional.normalize(torch.randn(400, 3, generator=g), dim=-1)
    p = torch.tensor([params])
    q_d, q_a = field.param_features(p)
    frame = FrameField(field, q_d, q_a, compiled=compiled)
    assert frame.compiled == (compiled and vm_kernel.available(points.device))
    with torch.no_grad():
        assert torch.allclose(frame.density(points), field.density(points, q_d.expand(400, -1)), rtol=1e-5, atol=1e-6)
        colour = frame.color(points, frame.direction_terms(dirs))
        assert torch.allclose(colour, field.color(points, dirs, q_a.expand(400, -1), q_d.expand(400, -1)), atol=1e-6)


def _both_renders(field, settings: RenderSettings, size: int = 24):
    intr = Intrinsics.from_fov(size, size, math.radians(40.0))
    c2w = torch.from_numpy(orbit_c2w(35.0, 25.0, 2.2)).float()
    params = torch.tensor([0.2, -0.4])
    with torch.no_grad():
        fast = render_image(field, c2w, intr, params, settings)
        rays_o, rays_d = image_rays(c2w, intr)
        rays_o, rays_d = rays_o.reshape(-1, 3), rays_d.reshape(-1, 3)
        bg = torch.tensor(settings.background).expand(rays_o.shape[0], 3)
        slow = render_rays(field, rays_o, rays_d, params.expand(rays_o.shape[0], 2), bg,
                           field.voxel_size() * settings.step_ratio, settings.max_samples, None, 0.0)
    return fast.reshape(-1, 3), slow["rgb"]


def test_exhaustive_settings_reproduce_the_training_renderer(field) -> None:
    settings = RenderSettings(use_occupancy=False, early_termination=False, weight_threshold_per_voxel=0.0, chunk_rays=97)
    fast, slow = _both_renders(field, settings)
    assert torch.allclose(fast, slow, atol=2e-5)


@pytest.mark.parametrize("density_scale", [1e-3, 1.0, 1e4])
def test_early_termination_error_is_bounded_by_its_threshold(field, density_scale) -> None:
    """A nearly transparent medium, a typical one and a stiff, nearly opaque one."""
    with torch.no_grad():
        field.density_decoder.out.bias.add_(math.log(density_scale))
    try:
        base = RenderSettings(use_occupancy=False, early_termination=False, weight_threshold_per_voxel=0.0, segment_samples=4)
        fast_settings = replace(base, early_termination=True, early_stop_eps=1e-4, weight_threshold_per_voxel=1e-5)
        exhaustive, _ = _both_renders(field, base)
        fast, _ = _both_renders(field, fast_settings)
        assert torch.isfinite(fast).all()
        # Dropped light is at most the transmittance left (1e-4) plus the skipped weights.
        assert (fast - exhaustive).abs().max() < 5e-4
    finally:
        with torch.no_grad():
            field.density_decoder.out.bias.sub_(math.log(density_scale))


def test_scaled_render_is_the_small_render_upsampled(field) -> None:
    from visnerf.rendering.renderer import render_image_scaled

    intr = Intrinsics.from_fov(20, 14, math.radians(40.0))
    c2w = torch.from_numpy(orbit_c2w(35.0, 25.0, 2.2)).float()
    params = torch.tensor([0.2, -0.4])
    full = RenderSettings()
    with torch.no_grad():
        assert torch.equal(render_image_scaled(field, c2w, intr, params, full), render_image(field, c2w, intr, params, full))
        half = replace(full, resolution_scale=0.5)
        small = render_image(field, c2w, intr.scaled(10, 7), params, half)
        expected = torch.nn.functional.interpolate(small.permute(2, 0, 1)[None], size=(14, 20), mode="bilinear",
                                                   align_corners=False)[0].permute(1, 2, 0)
        scaled = render_image_scaled(field, c2w, intr, params, half)
    assert scaled.shape == (14, 20, 3) and torch.allclose(scaled, expected)


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "torch"])
@pytest.mark.parametrize("params", [(-1.0, -1.0), (0.3, -0.2)])
def test_bf16_decoders_differ_from_float32_only_by_rounding(field, params, compiled) -> None:
    """bfloat16 products keep 8 significant bits: a relative error of a few 1e-3 per value."""
    g = torch.Generator().manual_seed(2)
    n = 40000  # more than one SUB_CHUNK pass
    points = torch.rand(n, 3, generator=g) - 0.5
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    q_d, q_a = field.param_features(torch.tensor([params]))
    exact, rounded = FrameField(field, q_d, q_a), FrameField(field, q_d, q_a, torch.bfloat16, compiled=compiled)
    with torch.no_grad():
        sigma, sigma_b = exact.density(points), rounded.density(points)
        colour = exact.color(points, exact.direction_terms(dirs))
        colour_b = rounded.color(points, rounded.direction_terms(dirs))
    assert sigma_b.dtype == colour_b.dtype == torch.float32
    assert torch.isfinite(sigma_b).all() and torch.isfinite(colour_b).all()
    rel = (sigma_b - sigma).abs() / sigma.abs().clamp_min(1e-3)
    assert float(rel.median()) < 1e-2 and float(rel.max()) < 0.1
    assert float((colour_b - colour).abs().max()) < 2e-2
    assert float((colour_b - colour).abs().mean()) < 2e-3
    # Not the float32 path under another name: the rounding is there.
    assert not torch.equal(colour_b, colour)


def test_bf16_frames_stay_close_to_the_exhaustive_float32_frames(field, monkeypatch) -> None:
    from visnerf.rendering import renderer

    monkeypatch.setattr(renderer, "bf16_native", lambda device: True)  # the bf16 path on any CPU
    base = RenderSettings(use_occupancy=False, early_termination=False, weight_threshold_per_voxel=0.0)
    exact, _ = _both_renders(field, base)
    rounded, _ = _both_renders(field, replace(base, bf16=True))
    mse = float(((rounded - exact) ** 2).mean())
    assert mse > 0.0 and 10.0 * math.log10(1.0 / mse) > 45.0


def test_bf16_frames_are_float32_frames_where_the_cpu_has_no_bf16_units(field, monkeypatch) -> None:
    from visnerf.rendering import renderer

    monkeypatch.setattr(renderer, "bf16_native", lambda device: False)
    base = RenderSettings(use_occupancy=False, early_termination=False, weight_threshold_per_voxel=0.0)
    exact, _ = _both_renders(field, base)
    asked, _ = _both_renders(field, replace(base, bf16=True))
    assert torch.equal(asked, exact)


def test_qualities_derive_from_the_checkpoint_render_config() -> None:
    from visnerf.config import RenderConfig

    cfg = RenderConfig(step_ratio=0.5, full_step_ratio=1.0, preview_step_factor=2.0, preview_scale=0.5, bf16=True)
    full = RenderSettings.from_config(cfg, (1.0, 1.0, 1.0), "full")
    plain = RenderSettings.from_config(cfg, (1.0, 1.0, 1.0), "exhaustive")
    preview = RenderSettings.from_config(cfg, (1.0, 1.0, 1.0), "preview")
    assert (full.step_ratio, full.use_occupancy, full.early_termination, full.bf16) == (1.0, True, True, True)
    # the exhaustive reference marches the model's occupancy grid (part of the model), every sample in it
    assert (plain.step_ratio, plain.use_occupancy, plain.early_termination, plain.bf16) == (0.5, True, False, False)
    assert plain.weight_threshold_per_voxel == 0.0
    assert (preview.step_ratio, preview.resolution_scale) == (1.0, 0.5)
    # refused by the run-time type check under test, by the value check where that is off
    with pytest.raises((ValueError, TypeError), match="quality"):
        RenderSettings.from_config(cfg, (1.0, 1.0, 1.0), "fast")
    # A model trained with coarser samples is still judged against frames sampled half a voxel apart.
    coarse = RenderConfig(step_ratio=1.0)
    assert RenderSettings.from_config(coarse, (1.0, 1.0, 1.0), "exhaustive").step_ratio == 0.5
    assert RenderSettings.from_config(coarse, (1.0, 1.0, 1.0), "preview").step_ratio == 1.0
    assert RenderSettings.from_config(RenderConfig(step_ratio=0.25), (1.0, 1.0, 1.0), "exhaustive").step_ratio == 0.25


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("rows", [1, 37, 1024])
def test_linear_relu_equals_the_plain_product(dtype, rows, monkeypatch) -> None:
    from visnerf.representation import linear_relu as lr

    g = torch.Generator().manual_seed(rows)
    x, w, b = (torch.randn(*s, generator=g).to(dtype) for s in ((rows, 63), (128, 63), (128,)))
    expected = torch.relu(x.double() @ w.double().t() + b.double())
    with torch.inference_mode():
        got = lr.linear_relu(x, w, b)
        monkeypatch.setattr(lr, "_fused_ok", {dtype: False})  # the fallback where oneDNN's fused op is missing
        plain = lr.linear_relu(x, w, b)
    assert got.dtype == plain.dtype == dtype and got.shape == (rows, 128)
    assert (got >= 0).all() and (plain >= 0).all()
    tol = 1e-4 if dtype == torch.float32 else 0.1  # bf16 rounds the output to 8 bits (values up to ~30)
    assert torch.allclose(got.double(), expected, atol=tol, rtol=1e-2 if dtype == torch.bfloat16 else 1e-5)
    assert torch.allclose(plain.double(), expected, atol=tol, rtol=1e-2 if dtype == torch.bfloat16 else 1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_linear_relu_takes_the_plain_path_where_onednn_refuses_the_dtype(dtype, monkeypatch) -> None:
    """As on a CPU without bf16 instructions, where oneDNN cannot create the bfloat16 kernel."""
    from visnerf.representation import linear_relu as lr

    def refuse(*args):
        raise RuntimeError("could not create a primitive descriptor for the inner product forward propagation primitive")

    monkeypatch.setattr(lr, "_fused_ok", {})
    monkeypatch.setattr(lr, "_fused_op", lambda: refuse)
    x, w, b = torch.randn(9, 6).to(dtype), torch.randn(4, 6).to(dtype), torch.randn(4).to(dtype)
    with torch.inference_mode():
        got = lr.linear_relu(x, w, b)
    assert lr._fused_ok == {dtype: False}
    assert torch.equal(got, lr.plain_linear_relu(x, w, b))


def test_linear_relu_keeps_gradients_on_the_plain_path() -> None:
    from visnerf.representation.linear_relu import linear_relu

    w = torch.randn(8, 5, requires_grad=True)
    y = linear_relu(torch.randn(4, 5), w, torch.zeros(8))
    y.sum().backward()
    assert w.grad is not None and torch.isfinite(w.grad).all()


@pytest.mark.parametrize("n_freqs", [0, 2, 4])
def test_position_encoding_written_in_place_equals_the_reference(n_freqs) -> None:
    from visnerf.representation.decoders import encode_position, encode_position_into, positional_encoding_dim

    points = torch.rand(500, 3, generator=torch.Generator().manual_seed(3)) * 2 - 1
    out = torch.empty(500, positional_encoding_dim(n_freqs))
    encode_position_into(points, n_freqs, out)
    # The cosines are sines a quarter turn on: one float32 rounding of angles up to 2^L pi.
    assert torch.allclose(out, encode_position(points, n_freqs), atol=2e-6 * 2.0**n_freqs, rtol=0)
    half = torch.empty(500, positional_encoding_dim(n_freqs), dtype=torch.bfloat16)
    encode_position_into(points, n_freqs, half)
    assert torch.allclose(half.float(), encode_position(points, n_freqs), atol=8e-3, rtol=0)


# Measured 50.4, 152 and 100 dB; without the unshaded weight's mean colour the dense medium's
# frame is 59 dB from the exhaustive one (the faint one shades no sample: nothing to correct).
@pytest.mark.parametrize(("density_scale", "min_db"), [(1e-2, 45.0), (1.0, 90.0), (30.0, 80.0)])
def test_full_quality_thresholds_stay_close_to_the_exhaustive_frame(field, density_scale, min_db) -> None:
    """The shipped full-quality thresholds (early stop 1e-4, colour above a weight of 2e-3 a voxel with
    the unshaded weight given the ray's mean colour) at the exhaustive spacing, on a faint, a
    typical and a dense medium: what they drop is bounded by the weight they skip."""
    cfg = RenderConfig()
    full = RenderSettings.from_config(cfg, (1.0, 1.0, 1.0), "full")
    assert full.weight_threshold_per_voxel == cfg.full_weight_threshold_per_voxel == 2e-3
    with torch.no_grad():
        field.density_decoder.out.bias.add_(math.log(density_scale))
    try:
        base = RenderSettings(use_occupancy=False, early_termination=False, weight_threshold_per_voxel=0.0)
        exhaustive, _ = _both_renders(field, base)
        fast, _ = _both_renders(field, replace(base, early_termination=True, early_stop_eps=full.early_stop_eps,
                                               weight_threshold_per_voxel=full.weight_threshold_per_voxel))
    finally:
        with torch.no_grad():
            field.density_decoder.out.bias.sub_(math.log(density_scale))
    assert torch.isfinite(fast).all()
    mse = float(((fast - exhaustive) ** 2).mean())
    assert mse == 0.0 or 10.0 * math.log10(1.0 / mse) > min_db
    assert float((fast - exhaustive).abs().max()) < 0.02
