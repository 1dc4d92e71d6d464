"""Extreme-case matrix of the volume renderer, each case against an independent float64 reference
(docs/numerics.md tabulates the cases and bounds).

- Compositing: optical depths per sample from 1e-8 to 1e8, one sample, 4096 samples, empty and
  opaque rays, through the float32 functions of ``rendering.volume``, the training path's shading
  (``shade_rays``) and the inference march (``march_rays``), with densities and colours given per
  sample. Reference: a plain float64 loop of ``C = sum_i T_i (1 - exp(-tau_i)) c_i + T_final bg``.
- Geometry: the real renderers on a field of constant density and colour (the decoders' output
  layers set to constants) for axis-parallel, grazing, corner and inside-the-box rays, against a
  float64 slab intersection and ``1 - exp(-sigma * length)``.
- Parameters exactly at and a hair (1e-7 normalised) inside the ends of their range, and a
  training step on targets that are all background.
"""

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest
import torch

from visnerf.config import TrainConfig
from visnerf.data.cameras import Intrinsics, image_rays, orbit_c2w
from visnerf.data.scene import SceneData, axes_from_values
from visnerf.rendering.density_gradients import DensityGradientSampling
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.render_settings import RenderSettings
from visnerf.rendering.renderer import empty_space_of, march_rays, render_image
from visnerf.rendering.training_render import RaySamples, drop_occluded, place_samples, render_rays, shade_rays
from visnerf.rendering.volume import (
    accumulate_along_rays,
    composite_background,
    optical_depths,
    render_weight_from_density,
    weights_from_optical_depth,
)
from visnerf.representation.field import VisNerfField
from visnerf.representation.frame_field import FrameField, SampleTaps
from visnerf.representation.vm_taps import VMTaps
from visnerf.testing import make_tiny_field
from visnerf.training.step import occupied_windows
from visnerf.training.trainer import Trainer

# ---------------------------------------------------------------------------------------------
# Bounds. s: samples on the ray; S_i: the optical depth before sample i; "observed": the largest
# error over this file's cases (x86-64 CPU, torch 2.13).
# ---------------------------------------------------------------------------------------------

U = 2.0**-24
"""float32 unit roundoff (6.0e-8)."""

TINY32 = torch.finfo(torch.float32).tiny
"""Smallest normal float32 (1.2e-38): exp(-S) for S > 87 is denormal, for S > 103.3 zero."""


def weight_rtol(s: int, before: torch.Tensor) -> torch.Tensor:
    """Relative bound on a weight or transmittance: ``(4 + sqrt(s) * S_i) * u``.

    w_i = exp(-S_i) * -expm1(-tau_i): the two factors are rounded to a few u (the 4), and S_i, a
    float32 cumulative sum (in segments, as the renderers march), carries an absolute error of up
    to s roundings of at most u * S_i each, which add as a random walk (sqrt(s) of them); exp(-S)
    turns an absolute error of S into the same relative error of T. Observed: at most 0.38 of the
    bound (5.4e-6 relative, 4096 samples of tau 1e-3 in segments of 16; 1.6e-6 for 64 samples or
    fewer). float32 cannot hold a weight below TINY32 to a relative bound (denormal or 0): there
    only |w - w_ref| <= TINY32 is asserted, with w >= 0 and finite."""
    return (4.0 + math.sqrt(s) * before) * U


def colour_atol(s: int) -> float:
    """Absolute bound on a composited colour channel (colours, background in [0, 1]):
    ``(4 + sqrt(s)) * u``. A few roundings per term, and the float32 sum of s weighted colours
    (einsum / index_add) rounds as a random walk. Observed: 1.0e-6 against 4.1e-6 at 4096 samples
    of tau 1e-3; 7.8e-8 against 7.2e-7 at 64 samples."""
    return (4.0 + math.sqrt(s)) * U


WEIGHT_SUM_SLACK = 1e-6
"""sum(w) <= 1 + this. sum(w) telescopes to 1 - T_final <= 1; each weight is rounded to a few u
and the sum adds its own rounding. Observed: sum(w) <= 1 exactly, in every case."""

OPACITY_ATOL = 1e-6
"""|opacity - opacity_ref| and |sum(w) - opacity_ref|. Opacity is ``-expm1(-sum tau)``: the float32
sum's relative error, times sum * exp(-sum) <= 1/e. sum(w) is a sum of s rounded weights.
Observed: 1.8e-8 (opacity), 2.6e-7 (sum of 4096 weights of tau 1e-3, in segments)."""

GRAD_ATOL = 1e-6
"""|dC/dtau_k - ref| per sample (dC/dsigma = delta * dC/dtau, delta = 0.5), C summed over its
three channels. The exact gradient is sum_ch T_{k+1} c_k - (the light behind sample k), a
difference of terms in [0, 3] whose second part autograd forms as a reverse cumulative sum over
the ray: float32 meets an absolute bound of a few u per term summed, not a relative one (where
the terms cancel, observed relative errors reach 2.7 at |grad| ~ 1e-8). Where tau_k ~ 1e8, or the
ray is already opaque, the gradient is exactly 0 in float64 as in float32 (exp(-tau) underflows
in both, and the backward of exp(-S) multiplies by exp(-S) = 0, never by its inverse): what
guards it is that it stays finite. Observed: 4.8e-7 (4096 samples), 3.2e-7 for 64 or fewer."""

WEIGHT_ATOL = 2e-7
"""|dC/dc - w_ref| (the gradient w.r.t. a sample's colour is its weight) and the slack by which a
weight counts as "at the colour threshold". A weight is in [0, 1]; its relative error is
``weight_rtol`` and |w| * (4 + sqrt(s) S) u * exp(-S) peaks far below this. Observed: 2.8e-8."""

RANGE_SLACK = 1e-6
"""Colours in [0 - slack, 1 + slack]: a convex combination of values in [0, 1] with weights that
sum to <= 1 + WEIGHT_SUM_SLACK."""

GEOMETRY_ATOL = 5e-7
"""|rgb - expected| for a constant-density field whose expected colour is computed from the
number of lattice samples inside the float64 box interval (``_lattice_count``): float32 sums of
n <= 25 equal optical depths, one ``expm1`` and the colour mix, ~(4 + sqrt(25)) u = 5.4e-7.
Observed: 1.8e-7."""

STOP_EPS = 1e-4
"""The training path drops samples behind transmittance below ``TrainConfig.stop_eps`` = 1e-4
(``drop_occluded``) and the inference march stops a ray there (``early_stop_eps``): at most that
much light goes missing, times |colour - background| <= 1."""

LATTICE_MARGIN = 1e-4
"""Fraction of a step by which a sample may sit on either side of the box's exit in float32
(t_near + step (i + 0.5) < t_far, with t ~ 3 and u * 3 ~ 2e-7, 3e-6 of a step): the expected
colour is taken between those of both sample counts."""

PARAM_HAIR_ATOL = 1e-6
"""|render(end) - render(end +- 1e-7)| (exhaustive). The parameter features are a monotone cubic
in the normalised value, whose slope is at most 3 times the tables' secants (here below 5 per
unit): a 1e-7 step moves them by at most 1.5e-6, and the render by about as much times the
decoders' gain: a few float32 ulps of a colour. Observed: 1.2e-7."""

DELTA = 0.5
"""Sample length of the compositing cases: a power of two, so that sigma = tau / DELTA and
sigma * DELTA are exact in float32 and the reference sees the same optical depths."""

BACKGROUND = (0.2, 0.5, 0.9)


# ---------------------------------------------------------------------------------------------
# Compositing cases and the float64 reference
# ---------------------------------------------------------------------------------------------


def _random_mix(n: int, s: int, seed: int) -> torch.Tensor:
    """Optical depths log-uniform over 1e-8 .. 1e8 (times a uniform factor)."""
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, s, generator=g) * 10.0 ** (torch.rand(n, s, generator=g) * 16.0 - 8.0)


TAU_CASES: dict[str, Callable[[], torch.Tensor]] = {
    "tau_1e-8_single": lambda: torch.tensor([[1e-8]]),
    "tau_1_single": lambda: torch.tensor([[1.0]]),
    "tau_1e8_single": lambda: torch.tensor([[1e8]]),
    "tau_logspace_up": lambda: torch.logspace(-8, 8, 33)[None],
    "tau_logspace_down": lambda: torch.logspace(8, -8, 33)[None],
    "tau_random_mix": lambda: _random_mix(32, 64, seed=0),
    "tau_1e7_after_small": lambda: torch.tensor([[0.3, 1e7, 0.5]]),
    "tau_1e8_after_tiny": lambda: torch.tensor([[1e-8] * 20 + [1e8] + [0.5] * 3]),
    "tau_1e-8_x4096": lambda: torch.full((2, 4096), 1e-8),
    "tau_1e-3_x4096": lambda: torch.full((2, 4096), 1e-3),
    "tau_random_x4096": lambda: torch.rand(2, 4096, generator=torch.Generator().manual_seed(1)) * 2e-3,
    "empty": lambda: torch.zeros(4, 32),
    "opaque_tau_1e8": lambda: torch.full((4, 32), 1e8),
    "opaque_tau_30": lambda: torch.full((4, 32), 30.0),  # T passes through the float32 denormals to 0
}


def _colours(tau: torch.Tensor) -> torch.Tensor:
    g = torch.Generator().manual_seed(tau.numel())
    return torch.rand(*tau.shape, 3, generator=g)


def reference(tau: torch.Tensor, colours: torch.Tensor, background: tuple[float, float, float],
              shaded: torch.Tensor | None = None) -> dict:
    """Plain float64 loop: T_i = exp(-sum_{j<i} tau_j), w_i = T_i (1 - exp(-tau_i)),
    C = sum_i w_i c_i + T_final bg, and dC/dtau_k (C summed over channels)
    = sum_ch [T_{k+1} c_k - (sum_{i>k} w_i c_i + T_final bg)].

    ``shaded`` (bool [n, s]): the samples whose colour the renderer evaluates; the others count
    with colour 0 (the training path's ``shade_rays`` evaluates colour only where the weight is
    above its threshold, so the rest add nothing to C and no colour term to dC/dtau)."""
    n, s = tau.shape
    if shaded is not None:
        colours = colours * shaded[..., None]
    taus, cols = tau.double().tolist(), colours.double().tolist()
    background = torch.tensor(background).double().tolist()  # as the renderers get it, in float32
    w = np.zeros((n, s))
    before_i = np.zeros((n, s))
    trans = np.zeros((n, s))
    rgb = np.zeros((n, 3))
    opacity = np.zeros(n)
    grad = np.zeros((n, s))
    for r in range(n):
        before = 0.0
        for i in range(s):
            before_i[r, i] = before
            trans[r, i] = math.exp(-before)
            w[r, i] = trans[r, i] * -math.expm1(-taus[r][i])
            for ch in range(3):
                rgb[r, ch] += w[r, i] * cols[r][i][ch]
            before += taus[r][i]
        t_final = math.exp(-before)
        opacity[r] = -math.expm1(-before)
        behind = [t_final * b for b in background]
        for ch in range(3):
            rgb[r, ch] += behind[ch]
        for k in range(s - 1, -1, -1):
            t_next = trans[r, k] * math.exp(-taus[r][k])
            grad[r, k] = sum(t_next * cols[r][k][ch] - behind[ch] for ch in range(3))
            for ch in range(3):
                behind[ch] += w[r, k] * cols[r][k][ch]
    mask = torch.ones(n, s, dtype=torch.float64) if shaded is None else shaded.double()
    arrays = {"weights": w, "trans": trans, "rgb": rgb, "opacity": opacity, "grad_tau": grad, "before": before_i}
    return {"grad_colour_mask": mask, **{k: torch.from_numpy(v) for k, v in arrays.items()}}


def _close(actual: torch.Tensor, expected: torch.Tensor, atol: float, what: str) -> None:
    err = float((actual.double() - expected).abs().max()) if actual.numel() else 0.0
    assert err <= atol, f"{what}: |error| {err:.3g} > {atol:.3g}"


def _check_weights(w: torch.Tensor, trans: torch.Tensor, ref: dict) -> None:
    assert torch.isfinite(w).all() and torch.isfinite(trans).all()
    assert bool((w >= 0).all()) and float(w.sum(-1).max()) <= 1.0 + WEIGHT_SUM_SLACK
    assert bool((trans >= 0).all() and (trans <= 1).all())
    assert bool((trans[:, 1:] <= trans[:, :-1]).all()), "transmittance increases along the ray"
    rtol = weight_rtol(w.shape[1], ref["before"])
    for name, actual, expected in (("weights", w, ref["weights"]), ("transmittance", trans, ref["trans"])):
        excess = (actual.double() - expected).abs() - rtol * expected
        assert float(excess.max()) <= TINY32, f"{name}: relative error above (4 + sqrt(s) S) u"
    _close(w.sum(-1), ref["opacity"], OPACITY_ATOL, "sum of weights")


def _check_colour(rgb: torch.Tensor, opacity: torch.Tensor, ref: dict) -> None:
    assert torch.isfinite(rgb).all() and torch.isfinite(opacity).all()
    assert bool((opacity >= 0).all() and (opacity <= 1).all())
    assert float(rgb.min()) >= -RANGE_SLACK and float(rgb.max()) <= 1.0 + RANGE_SLACK
    _close(opacity, ref["opacity"], OPACITY_ATOL, "opacity")
    _close(rgb, ref["rgb"], colour_atol(ref["weights"].shape[1]), "colour")


def _check_gradients(grad_sigma: torch.Tensor, grad_colour: torch.Tensor | None, ref: dict) -> None:
    if grad_colour is None:  # no sample shaded: shading skips samples of weight 0
        grad_colour = torch.zeros(*grad_sigma.shape, 3)
    assert torch.isfinite(grad_sigma).all() and torch.isfinite(grad_colour).all()
    _close(grad_sigma / DELTA, ref["grad_tau"], GRAD_ATOL, "dC/dtau")
    expected = (ref["weights"] * ref["grad_colour_mask"])[..., None].expand(grad_colour.shape)
    _close(grad_colour, expected, WEIGHT_ATOL, "dC/dcolour")


@pytest.mark.parametrize("case", list(TAU_CASES))
def test_volume_compositing(case: str) -> None:
    """``render_weight_from_density`` / ``weights_from_optical_depth`` / ``composite_background``
    in float32 against the float64 loop, values and gradients."""
    tau = TAU_CASES[case]()
    sigma = (tau / DELTA).requires_grad_()
    colours = _colours(tau).requires_grad_()
    deltas = torch.full_like(tau, DELTA)
    w, trans, alpha = render_weight_from_density(sigma, deltas)
    opacity = -torch.expm1(-optical_depths(sigma, deltas).sum(-1))
    rgb = composite_background(accumulate_along_rays(w, colours), opacity, torch.tensor(BACKGROUND))
    rgb.sum().backward()
    ref = reference(tau, colours.detach(), BACKGROUND)
    assert bool((alpha >= 0).all() and (alpha <= 1).all())
    _check_weights(w.detach(), trans.detach(), ref)
    _check_colour(rgb.detach(), opacity.detach(), ref)
    _check_gradients(sigma.grad, colours.grad, ref)
    # The renderers composite in segments, carrying the optical depth before each.
    parts, before = [], torch.zeros(tau.shape[0])
    for start in range(0, tau.shape[1], 16):
        seg = tau[:, start:start + 16]
        parts.append(weights_from_optical_depth(seg, before))
        before = before + seg.sum(-1)
    _check_weights(torch.cat(parts, dim=1), trans.detach(), ref)


# --- the production shading paths, with the densities and colours of the case per sample ------


def _lookup(table: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``table[ray, sample]`` at points placed at x = sample + 0.5, y = ray."""
    return table[points[:, 1].round().long(), points[:, 0].floor().long()]


def _index_taps(points: torch.Tensor) -> VMTaps:
    """VM taps of the right shape for ``points`` (the patched field reads the samples' points)."""
    m = points.shape[0]
    return VMTaps(torch.zeros(m, 3, 4, dtype=torch.long), torch.zeros(m, 3, 4), torch.zeros(m, 3, 2, dtype=torch.long),
                  torch.zeros(m, 3, 2))


def _table_field(monkeypatch: pytest.MonkeyPatch, sigma: torch.Tensor, colours: torch.Tensor) -> VisNerfField:
    """A real field whose density and colour (both branches: training ``density`` / ``color``,
    inference ``FrameField``) are read from per-(ray, sample) tables, in a box whose lattice at
    step 1 puts sample i of ray r at (i + 0.5, r, 0)."""
    n, s = sigma.shape
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=0)
    field.aabb = torch.tensor([[0.0, -0.5, -0.5], [float(s), n - 0.5, 0.5]])
    monkeypatch.setattr(VisNerfField, "voxel_size", lambda self: 1.0)
    monkeypatch.setattr(VisNerfField, "density", lambda self, points, q: _lookup(sigma, points))
    monkeypatch.setattr(VisNerfField, "color", lambda self, points, dirs, q: _lookup(colours, points))
    monkeypatch.setattr(FrameField, "lookup", lambda self, points: SampleTaps(points, points, _index_taps(points)))
    monkeypatch.setattr(FrameField, "density_at", lambda self, samples: _lookup(sigma, samples.points).detach())
    monkeypatch.setattr(FrameField, "color_at", lambda self, samples, terms: _lookup(colours, samples.points).detach())
    return field


def _skippable_weight(ref: dict, threshold: float) -> torch.Tensor:
    """Per ray, the reference weight of the samples a colour threshold may leave unshaded."""
    w = ref["weights"]
    return torch.where(w <= threshold + WEIGHT_ATOL, w, 0.0).sum(-1)


SHADING = {
    "all_shaded": (0.0, None),
    "threshold_1e-4": (1e-4, None),
    "sampled_density_grads": (1e-4, 0.125),
}
"""(colour threshold, ``density_grad_keep``) of ``shade_rays``: every sample of non-zero weight
shaded; the training default (weights above 1e-4); and the default with the training step's
sampled density gradients (alpha below 1e-4 back-propagated at random, 1 in 8, times 8)."""


@pytest.mark.parametrize("shading", list(SHADING))
@pytest.mark.parametrize("case", list(TAU_CASES))
def test_training_shading(case: str, shading: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """``shade_rays`` (the training step's differentiable pass) with the case's densities.
    With a colour threshold the samples left unshaded lose at most their weight. An unshaded
    sample (weight at or below the threshold: at threshold 0, a weight of exactly 0) also gets no
    colour term T_{k+1} c_k in dC/dsigma_k, as its colour is never evaluated (TensoRF's colour
    mask); the gradients are checked against the reference with those colours taken as 0."""
    threshold, keep = SHADING[shading]
    tau = TAU_CASES[case]()
    n, s = tau.shape
    sigma = (tau / DELTA).requires_grad_()
    colours = _colours(tau).requires_grad_()
    field = _table_field(monkeypatch, sigma, colours)
    x = torch.arange(s, dtype=torch.float32)[None, :].expand(n, s) + 0.5
    y = torch.arange(n, dtype=torch.float32)[:, None].expand(n, s)
    samples = RaySamples(torch.stack([x, y, torch.zeros(n, s)], dim=-1), torch.full((n, s), DELTA),
                         torch.ones(n, s, dtype=torch.bool))
    rays_d = torch.tensor([[1.0, 0.0, 0.0]]).expand(n, 3)
    grads = None if keep is None else DensityGradientSampling(1e-4, keep, torch.Generator().manual_seed(4))
    out = shade_rays(field, rays_d, torch.zeros(n, 1), torch.tensor(BACKGROUND).expand(n, 3), samples, threshold,
                     grads)
    if out["rgb"].requires_grad:  # not when no sample is shaded nor drawn for the density gradient
        out["rgb"].sum().backward()
    grad_sigma = torch.zeros_like(sigma) if sigma.grad is None else sigma.grad
    # Against the whole ray: the unshaded samples lose at most their weight (0 at threshold 0).
    full = reference(tau, colours.detach(), BACKGROUND)
    bound = colour_atol(s) + _skippable_weight(full, threshold)[:, None]
    assert bool(((out["rgb"].detach().double() - full["rgb"]).abs() <= bound).all())
    # Against the ray with the unshaded samples' colour taken as 0, as ``shade_rays`` takes it
    # (which samples are shaded: the float32 weights' test against the threshold).
    shaded = weights_from_optical_depth(tau) > threshold
    ref = reference(tau, colours.detach(), BACKGROUND, shaded)
    _check_colour(out["rgb"].detach(), out["opacity"].detach(), ref)
    if keep is None:
        _check_gradients(grad_sigma, colours.grad, ref)
        return
    # Sampled: exact where alpha >= 1e-4; elsewhere 0 (not drawn) or 1 / keep times exact (drawn).
    low = -torch.expm1(-tau) < 1e-4
    _check_gradients(torch.where(low, 0.0, grad_sigma), colours.grad,
                     {**ref, "grad_tau": torch.where(low, 0.0, ref["grad_tau"])})
    drawn = low & (grad_sigma != 0)
    _close(grad_sigma[drawn] * keep / DELTA, ref["grad_tau"][drawn], GRAD_ATOL, "sampled dC/dtau")


MARCH_SETTINGS = {
    "exhaustive": RenderSettings(step_ratio=1.0, use_occupancy=False, early_termination=False,
                                 weight_threshold_per_voxel=0.0),
    "fast": RenderSettings(step_ratio=1.0, use_occupancy=False),
}


@pytest.mark.parametrize("settings", list(MARCH_SETTINGS))
@pytest.mark.parametrize("case", list(TAU_CASES))
def test_inference_march(case: str, settings: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """``march_rays`` (frames) with the case's densities, in segments of 16 then 32, 64, 128
    samples. The fast settings stop a ray below transmittance 1e-4 and shade only samples of weight
    above 1e-4 (giving the rest the ray's mean colour): the error is at most the light left at the
    stop plus the weight of the samples left unshaded."""
    tau = TAU_CASES[case]()
    n, s = tau.shape
    colours = _colours(tau)
    field = _table_field(monkeypatch, tau, colours)  # step 1: sigma = tau
    cfg = replace(MARCH_SETTINGS[settings], max_samples=s)
    rays_o = torch.stack([torch.full((n,), -1.0), torch.arange(n, dtype=torch.float32), torch.zeros(n)], dim=-1)
    rays_d = torch.tensor([[1.0, 0.0, 0.0]]).expand(n, 3).contiguous()
    q_d, q_a = field.param_features(torch.zeros(1, 1))
    with torch.inference_mode():
        rgb = march_rays(field, rays_o, rays_d, FrameField(field, q_d, q_a), torch.tensor(BACKGROUND), cfg, None)
    ref = reference(tau, colours, BACKGROUND)
    assert torch.isfinite(rgb).all()
    assert float(rgb.min()) >= -RANGE_SLACK and float(rgb.max()) <= 1.0 + RANGE_SLACK
    if settings == "exhaustive":
        _close(rgb, ref["rgb"], colour_atol(ref["weights"].shape[1]), "colour")
    else:
        bound = colour_atol(s) + cfg.early_stop_eps + _skippable_weight(ref, cfg.weight_threshold_per_voxel)[:, None]
        assert bool(((rgb.double() - ref["rgb"]).abs() <= bound).all())


# ---------------------------------------------------------------------------------------------
# Geometry through the real renderers: a field of constant density and colour
# ---------------------------------------------------------------------------------------------

LO, HI = -0.5, 0.5  # make_tiny_field's box, on every axis
HAIR = 1e-7 * (HI - LO) / 2  # 1e-7 in normalised [-1, 1] coordinates
COLOUR = (0.1, 0.6, 0.95)
GEOMETRY_BACKGROUND = (1.0, 0.0, 0.3)
DENSITIES = {"empty": 0.0, "haze": 2.0, "dense": 60.0, "opaque": 1e8, "empty_grid": 2.0}
"""Per world unit; the step is 1/14 (half of a 1/7 voxel): haze reaches optical depth 3.5 across
the diagonal, dense 4.3 per sample (the stop at transmittance 1e-4 comes after 3 samples, with
light left), opaque 7e6 per sample. ``empty_grid``: haze, behind an occupancy grid with no cell."""


def _constant_field(sigma: float, seed: int = 0) -> VisNerfField:
    """``make_tiny_field`` with both decoders' output layers constant: density ``sigma`` (exactly 0
    for 0: softplus(-200) underflows) and colour ``COLOUR`` everywhere."""
    field, _ = make_tiny_field([("a", [0.0, 1.0])], seed=seed)
    raw = -200.0 if sigma == 0.0 else (sigma if sigma > 20.0 else math.log(math.expm1(sigma)))
    with torch.no_grad():
        field.density_decoder.out.weight.zero_()
        field.density_decoder.out.bias.fill_(raw - field.cfg.density_shift)
        field.color_decoder.out.weight.zero_()
        field.color_decoder.out.bias.copy_(torch.logit(torch.tensor(COLOUR, dtype=torch.float64)).float())
    return field


def _unit(d: list[list[float]]) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.tensor(d, dtype=torch.float64), dim=-1).float()


def _geometry_rays(name: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(origins, unit directions) of a named set of rays, float32."""
    vals = [LO, -0.3, 0.0, 0.25, HI]
    signs = [(sx, sy, sz) for sx in (-1.0, 1.0) for sy in (-1.0, 1.0) for sz in (-1.0, 1.0)]
    if name == "axis_parallel":  # direction components exactly 0, origins on faces and edges too
        o = [[-2.0, y, z] for y in vals for z in vals] + [[y, z, 2.0] for y in vals for z in vals]
        d = [[1.0, 0.0, 0.0]] * 25 + [[0.0, 0.0, -1.0]] * 25
        return torch.tensor(o), torch.tensor(d)
    if name == "axis_parallel_signed_zero":  # -0.0 components; two rays miss the box beside a face
        o = [[y, 2.0, z] for y in vals for z in vals] + [[0.6, 2.0, 0.0], [0.0, 2.0, -0.6]]
        return torch.tensor(o), torch.tensor([[-0.0, -1.0, -0.0]] * 27)
    if name == "face_hair_inside":  # parallel to a face, a hair inside it
        o = [[HI - HAIR, y, -2.0] for y in vals] + [[y, LO + HAIR, -2.0] for y in vals]
        return torch.tensor(o), torch.tensor([[0.0, 0.0, 1.0]] * 10)
    if name == "face_hair_outside":  # parallel to a face, a hair outside it: all miss
        o = [[HI + HAIR, y, -2.0] for y in vals] + [[y, LO - HAIR, -2.0] for y in vals]
        return torch.tensor(o), torch.tensor([[0.0, 0.0, 1.0]] * 10)
    if name == "along_edges":
        o = [[x, y, -2.0] for x in (LO, HI) for y in (LO, HI)] + [[-2.0, y, z] for y in (LO, HI) for z in (LO, HI)]
        return torch.tensor(o), torch.tensor([[0.0, 0.0, 1.0]] * 4 + [[1.0, 0.0, 0.0]] * 4)
    if name == "corner_touch":  # lines that meet the box at one corner only
        d = _unit([[sx, sy, -sz] for sx, sy, sz in signs])
        corners = torch.tensor([[sx * HI, sy * HI, sz * HI] for sx, sy, sz in signs])
        return corners - 2.0 * d, d
    if name == "corner_diagonal":  # through two opposite corners
        d = _unit([[sx, sy, sz] for sx, sy, sz in signs])
        return -2.0 * d, d
    if name == "edge_clip":  # oblique rays cutting off a sliver of the box beside an edge
        eps = [1e-1, 1e-3, 1e-5, 1e-7, 0.0, -1e-7]
        o = [[HI - e / 2 - 2.0, HI - e / 2 + 2.0, 0.1] for e in eps]  # on the line x + y = 1 - e
        return torch.tensor(o), _unit([[1.0, -1.0, 0.0]] * len(eps))
    if name == "denormal_direction":  # components of 1e-40: (lo - o) / d overflows to +-inf
        o = [[x, y, -2.0] for x in vals for y in vals]
        return torch.tensor(o), torch.tensor([[1e-40, -1e-40, 1.0]] * 25)
    if name == "camera_inside":
        g = torch.Generator().manual_seed(2)
        axes = [[s * float(i == a) for i in range(3)] for a in range(3) for s in (1.0, -1.0)]
        d = torch.cat([torch.tensor(axes), _unit([list(s) for s in signs]),
                       torch.nn.functional.normalize(torch.randn(16, 3, generator=g), dim=-1)])
        return torch.tensor([[0.1, -0.2, 0.3]]).expand(len(d), 3).contiguous(), d
    if name == "origin_on_face":  # inward, outward, along the face, oblique
        d = torch.cat([torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                       _unit([[0.0, 1.0, 1.0], [1.0, 1.0, 1.0], [-1.0, 1.0, 1.0]])])
        return torch.tensor([[LO, 0.1, 0.2]]).expand(len(d), 3).contiguous(), d
    if name == "origin_on_corner":  # inward, outward, along edges and a face diagonal
        d = torch.cat([_unit([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0]]), torch.eye(3), _unit([[1.0, 1.0, 0.0]])])
        return torch.tensor([[LO, LO, LO]]).expand(len(d), 3).contiguous(), d
    raise KeyError(name)


GEOMETRY = ["axis_parallel", "axis_parallel_signed_zero", "face_hair_inside", "face_hair_outside", "along_edges",
            "corner_touch", "corner_diagonal", "edge_clip", "denormal_direction", "camera_inside", "origin_on_face",
            "origin_on_corner"]


def box_length(o: list[float], d: list[float]) -> float:
    """float64 slab method: length of the ray ``t >= 0`` inside the closed box [LO, HI]^3. An axis
    whose direction component is 0 constrains nothing when the origin lies in its slab (faces
    included) and excludes the ray otherwise."""
    t0, t1 = 0.0, math.inf
    for a in range(3):
        if d[a] == 0.0:
            if not LO <= o[a] <= HI:
                return 0.0
            continue
        ta, tb = (LO - o[a]) / d[a], (HI - o[a]) / d[a]
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    return max(0.0, t1 - t0)


def _lattice_count(length: float, step: float) -> int:
    """Samples at ``t_near + step * (i + 0.5)`` before ``t_far``: both renderers' deterministic
    lattice (``ray_windows``, ``place_samples`` without jitter)."""
    return max(0, math.ceil(length / step - 0.5))


def _colour_for_optical_depth(tau: np.ndarray, colour: np.ndarray, background: np.ndarray) -> np.ndarray:
    opacity = -np.expm1(-tau)[:, None]
    return colour[None] * opacity + background[None] * (1.0 - opacity)


def _expected_range(field: VisNerfField, rays_o: torch.Tensor, rays_d: torch.Tensor, step: float,
                    jittered: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per ray and channel: (low, high) of the colour from the lattice's sample count (within
    LATTICE_MARGIN), and (low, high) from the closed form ``1 - exp(-sigma L)`` with the length
    off by at most half a step (lattice) or a step (jittered), all float64."""
    with torch.no_grad():
        sigma = float(field.density(torch.zeros(1, 3), field.param_features(torch.zeros(1, 1))[0]))
    colour = 1.0 / (1.0 + np.exp(-field.color_decoder.out.bias.detach().double().numpy()))
    background = torch.tensor(GEOMETRY_BACKGROUND).double().numpy()  # as the renderers get it
    lengths = np.array([box_length(o, d) for o, d in zip(rays_o.double().tolist(), rays_d.double().tolist(),
                                                         strict=True)])
    counts = [(_lattice_count(x - LATTICE_MARGIN * step, step), _lattice_count(x + LATTICE_MARGIN * step, step))
              for x in lengths]
    lattice = [_colour_for_optical_depth(sigma * step * np.array([c[k] for c in counts], dtype=np.float64),
                                         colour, background) for k in (0, 1)]
    slack = step if jittered else step / 2
    closed = [_colour_for_optical_depth(sigma * np.clip(lengths + sign * slack, 0.0, None), colour, background)
              for sign in (-1.0, 1.0)]
    return (np.minimum(*lattice), np.maximum(*lattice), np.minimum(*closed), np.maximum(*closed))


def _background_only(expected: tuple) -> tuple:
    """The expected range of rays that meet no occupied cell: the background alone."""
    background = torch.tensor(GEOMETRY_BACKGROUND).double().numpy()
    return tuple(np.broadcast_to(background, e.shape) for e in expected)


def _assert_within(rgb: torch.Tensor, low: np.ndarray, high: np.ndarray, atol: float, what: str) -> None:
    x = rgb.detach().double().numpy()
    err = np.maximum(low - x, x - high).max()
    assert err <= atol, f"{what}: {err:.3g} outside the expected range (bound {atol:.3g})"


def _check_geometry_render(rgb: torch.Tensor, expected: tuple, atol: float, lattice: bool, sigma: float) -> None:
    rgb = rgb.detach()
    assert torch.isfinite(rgb).all()
    assert float(rgb.min()) >= -RANGE_SLACK and float(rgb.max()) <= 1.0 + RANGE_SLACK
    if lattice:
        _assert_within(rgb, expected[0], expected[1], atol, "lattice colour")
    _assert_within(rgb, expected[2], expected[3], atol, "closed form 1 - exp(-sigma L)")
    if sigma == 0.0:
        assert torch.equal(rgb, torch.tensor(GEOMETRY_BACKGROUND).expand_as(rgb)), "empty scene is not background"


def _geometry_setup(rays: str, density: str) -> tuple[VisNerfField, torch.Tensor, torch.Tensor, float]:
    field = _constant_field(DENSITIES[density])
    field.set_occupancy(torch.full((8, 8, 8), density != "empty_grid"))
    rays_o, rays_d = _geometry_rays(rays)
    return field, rays_o, rays_d, 0.0 if density in ("empty", "empty_grid") else DENSITIES[density]


@pytest.mark.parametrize("density", list(DENSITIES))
@pytest.mark.parametrize("rays", GEOMETRY)
def test_geometry_inference(rays: str, density: str) -> None:
    """``march_rays`` (what ``render_image`` runs per chunk) on a constant field: exhaustive, and
    with the frame renderer's defaults (occupancy windows, segments, early stop, colour threshold)."""
    field, rays_o, rays_d, sigma = _geometry_setup(rays, density)
    bg = torch.tensor(GEOMETRY_BACKGROUND)
    fast = RenderSettings(background=GEOMETRY_BACKGROUND)
    exhaustive = replace(fast, use_occupancy=False, early_termination=False, weight_threshold_per_voxel=0.0)
    step = field.voxel_size() * fast.step_ratio
    expected = _expected_range(field, rays_o, rays_d, step, jittered=False)
    if density == "empty_grid":
        expected = _background_only(expected)
    q_d, q_a = field.param_features(torch.zeros(1, 1))
    frame = FrameField(field, q_d, q_a)
    with torch.inference_mode():
        if density != "empty_grid":  # the exhaustive march ignores the grid
            rgb = march_rays(field, rays_o, rays_d, frame, bg, exhaustive, None)
            _check_geometry_render(rgb, expected, GEOMETRY_ATOL, True, sigma)
        rgb = march_rays(field, rays_o, rays_d, frame, bg, fast, EmptySpace.of(field.occupancy, field.aabb))
    _check_geometry_render(rgb, expected, GEOMETRY_ATOL + STOP_EPS, True, sigma)


@pytest.mark.parametrize("density", list(DENSITIES))
@pytest.mark.parametrize("rays", GEOMETRY)
def test_geometry_training(rays: str, density: str) -> None:
    """The training step's path (``place_samples``, ``drop_occluded``, ``shade_rays``) on a
    constant field, on the lattice, and jittered within the occupancy windows as a training step
    samples (``occupied_windows``), with the backward pass of the colour."""
    field, rays_o, rays_d, sigma = _geometry_setup(rays, density)
    n = rays_o.shape[0]
    step = field.voxel_size() * 0.5
    params, bg = torch.zeros(n, 1), torch.tensor(GEOMETRY_BACKGROUND).expand(n, 3)
    for generator in (None, torch.Generator().manual_seed(3)):
        # Jittered as a training step samples: within each ray's window of occupied cells.
        windows = None if generator is None else occupied_windows(field, rays_o, rays_d, step, empty_space_of(field))
        field.zero_grad(set_to_none=True)
        samples = place_samples(field, rays_o, rays_d, step, 1024, field.occupancy, generator, windows)
        samples = drop_occluded(field, samples, params, stop_eps=STOP_EPS)
        out = shade_rays(field, rays_d, params, bg, samples)
        if out["rgb"].requires_grad:
            out["rgb"].sum().backward()
        assert all(torch.isfinite(p.grad).all() for p in field.parameters() if p.grad is not None)
        opacity = out["opacity"].detach()
        assert torch.isfinite(opacity).all() and bool((opacity >= 0).all() and (opacity <= 1).all())
        expected = _expected_range(field, rays_o, rays_d, step, jittered=generator is not None)
        if density == "empty_grid":
            expected = _background_only(expected)
        _check_geometry_render(out["rgb"], expected, GEOMETRY_ATOL + STOP_EPS, generator is None, sigma)


CAMERAS = {
    "outside_orbit": (orbit_c2w(30.0, 20.0, 2.0), "haze"),
    "axis_aligned_outside": (np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2.0], [0, 0, 0, 1]]), "dense"),
    "inside_box": (orbit_c2w(30.0, 20.0, 0.3), "haze"),
    "inside_opaque": (orbit_c2w(30.0, 20.0, 0.3), "opaque"),
    "on_corner": (np.array([[1.0, 0, 0, LO], [0, 1, 0, LO], [0, 0, 1, HI], [0, 0, 0, 1]]), "dense"),
}


@pytest.mark.parametrize("settings", ["exhaustive", "fast"])
@pytest.mark.parametrize("camera", list(CAMERAS))
def test_render_image_cameras(camera: str, settings: str) -> None:
    """``render_image`` from cameras outside, inside the box, inside opaque content and on a
    corner of the box (half the rays start on its faces): every pixel against the lattice."""
    c2w, density = CAMERAS[camera]
    field = _constant_field(DENSITIES[density])
    field.set_occupancy(torch.ones(8, 8, 8, dtype=torch.bool))
    fast = RenderSettings(background=GEOMETRY_BACKGROUND)
    cfg = fast if settings == "fast" else replace(fast, use_occupancy=False, early_termination=False,
                                                  weight_threshold_per_voxel=0.0)
    intr = Intrinsics.from_fov(12, 12, math.radians(60.0))
    c2w = torch.from_numpy(c2w).float()
    with torch.inference_mode():
        rgb = render_image(field, c2w, intr, torch.tensor([0.0]), cfg).reshape(-1, 3)
    rays_o, rays_d = (r.reshape(-1, 3) for r in image_rays(c2w, intr))
    expected = _expected_range(field, rays_o, rays_d, field.voxel_size() * cfg.step_ratio, jittered=False)
    _check_geometry_render(rgb, expected, GEOMETRY_ATOL + (STOP_EPS if settings == "fast" else 0.0), True,
                           DENSITIES[density])
    if camera == "inside_opaque":
        _close(rgb, torch.tensor(COLOUR, dtype=torch.float64).expand(rgb.shape), GEOMETRY_ATOL, "opaque colour")


# ---------------------------------------------------------------------------------------------
# Parameters at the ends of their range
# ---------------------------------------------------------------------------------------------

END = 1.0
PARAMS = {  # (value, the range end it must match within PARAM_HAIR_ATOL, or exactly when clamped)
    "end_low": (-END, -END),
    "end_high": (END, END),
    "hair_inside_low": (-END + 1e-7, -END),
    "hair_inside_high": (END - 1e-7, END),
    "beyond_low": (-END - 1e-7, -END),
    "beyond_high": (END + 1e-7, END),
}


@pytest.fixture(scope="module")
def param_field() -> VisNerfField:
    """A tiny random field whose two parameter axes matter (uneven knots on the first)."""
    field, _ = make_tiny_field([("a", [0.0, 0.3, 1.0]), ("b", [2.0, 5.0])], seed=3)
    return field


def _param_frame(field: VisNerfField, value: float, settings: RenderSettings) -> torch.Tensor:
    intr = Intrinsics.from_fov(12, 12, math.radians(40.0))
    c2w = torch.from_numpy(orbit_c2w(30.0, 20.0, 2.0)).float()
    with torch.inference_mode():
        return render_image(field, c2w, intr, torch.tensor([value, value], dtype=torch.float32), settings)


@pytest.mark.parametrize("param", list(PARAMS))
def test_parameters_at_range_ends(param_field: VisNerfField, param: str) -> None:
    """Normalised parameters exactly at -1 / 1, a hair (1e-7) inside and outside: frames finite
    and in range; a hair inside renders within PARAM_HAIR_ATOL of the end, outside exactly as the
    end (clamped); the training path's gradients are finite."""
    value, end = PARAMS[param]
    value32 = float(torch.tensor(value, dtype=torch.float32))
    assert value32 != end or param.startswith("end")  # the hair survives float32
    exhaustive = RenderSettings(use_occupancy=False, early_termination=False, weight_threshold_per_voxel=0.0)
    for settings in (exhaustive, replace(exhaustive, use_occupancy=True, early_termination=True,
                                         weight_threshold_per_voxel=1e-4)):
        rgb = _param_frame(param_field, value, settings)
        assert torch.isfinite(rgb).all() and float(rgb.min()) >= 0.0 and float(rgb.max()) <= 1.0 + RANGE_SLACK
        if settings is exhaustive:
            at_end = _param_frame(param_field, end, settings)
            if param.startswith("beyond"):
                assert torch.equal(rgb, at_end), "a value beyond the range is not clamped to its end"
            _close(rgb, at_end.double(), PARAM_HAIR_ATOL, "parameter a hair from the end")
    q_d, q_a = param_field.param_features(torch.tensor([[value, value]]))
    assert torch.isfinite(q_d).all() and torch.isfinite(q_a).all()
    intr = Intrinsics.from_fov(8, 8, math.radians(40.0))
    rays_o, rays_d = (r.reshape(-1, 3) for r in image_rays(torch.from_numpy(orbit_c2w(0.0, 10.0, 2.0)).float(), intr))
    n = rays_o.shape[0]
    param_field.zero_grad(set_to_none=True)
    out = render_rays(param_field, rays_o, rays_d, torch.full((n, 2), value), torch.ones(n, 3),
                      param_field.voxel_size() * 0.5, 1024, None, generator=torch.Generator().manual_seed(0))
    out["rgb"].sum().backward()
    grads = [p.grad for p in param_field.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert all(bool(g.abs().sum() > 0) for g in (t.grad for t in param_field.density_params.tables))


# ---------------------------------------------------------------------------------------------
# A training step on targets that are all background
# ---------------------------------------------------------------------------------------------


def _background_scene(n_views: int = 4, size: int = 12) -> SceneData:
    values = np.array([[float(i % 2)] for i in range(n_views)])
    _, axes = axes_from_values(["t"], values)
    c2w = torch.stack([torch.from_numpy(orbit_c2w(360.0 / n_views * i, 20.0, 2.0)).float() for i in range(n_views)])
    return SceneData(
        images=torch.full((n_views, size, size, 3), 255, dtype=torch.uint8),  # white: the background
        c2w=c2w,
        intrinsics=Intrinsics.from_fov(size, size, math.radians(40.0)),
        params=torch.from_numpy(values).float(),
        param_axes=axes,
        view_ids=torch.arange(n_views),
        bbox=torch.tensor([[LO] * 3, [HI] * 3]),
    )


@pytest.mark.slow
@pytest.mark.parametrize("content", ["fresh_fog", "empty", "opaque"])
def test_training_step_on_all_background_targets(content: str) -> None:
    """``Trainer.train_step`` (stratified samples, ``drop_occluded``, sampled density gradients,
    micro-batches) on a batch whose every target pixel is background: finite loss, gradients and
    parameters after the step."""
    if content == "fresh_fog":
        field, _ = make_tiny_field([("t", [0.0, 1.0])], seed=1)
    else:
        field = _constant_field(0.0 if content == "empty" else 1e8, seed=1)
        field.set_param_knots([torch.tensor([-1.0, 1.0])])
        field.set_occupancy(torch.ones(8, 8, 8, dtype=torch.bool))  # samples within occupied windows
    cfg = TrainConfig(iterations=1, batch_rays=128, resolution_init=8, resolution_final=8, carve=False,
                      occupancy_resolution=8)
    trainer = Trainer(_background_scene(), None, cfg, torch.device("cpu"), init_field=field)
    stats = trainer.train_step()
    assert all(math.isfinite(v) for v in stats.values()), stats
    if content == "empty":
        assert stats["mse"] == 0.0  # an empty field already renders the white target
    for name, p in trainer.field.named_parameters():
        assert torch.isfinite(p).all(), name
        assert p.grad is None or torch.isfinite(p.grad).all(), name
