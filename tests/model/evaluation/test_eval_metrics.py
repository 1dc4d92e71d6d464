"""Metrics, CIELUV differences, placement in parameter space and the Pareto front, against hand values."""

import math

import numpy as np
import pytest
from skimage.color import rgb2luv

from visnerf.checkpoint import ParamAxis
from visnerf.evaluation.colour_difference import (
    DIFFERENCE_SCALE_MAX,
    colourize_difference,
    legend_colours,
    luv_difference,
    srgb_to_luv,
)
from visnerf.evaluation.metrics import psnr, ssim
from visnerf.evaluation.placement import classify, spacing_offset
from visnerf.evaluation.summary import json_safe
from visnerf.evaluation.sweeps import pareto_front
from visnerf.scenes.protocol import ParamAxis as SceneAxis
from visnerf.scenes.protocol import path_params

SHAPE = (32, 32, 3)


def test_psnr_of_known_pairs():
    zeros = np.zeros(SHAPE)
    # MSE 0.1^2 = 0.01: PSNR = 10 log10(1 / 0.01) = 20 dB
    assert psnr(zeros, np.full(SHAPE, 0.1)) == pytest.approx(20.0, abs=1e-9)
    # half the pixels off by 0.5: MSE = 0.5 * 0.25 = 0.125, PSNR = 10 log10(8) = 9.0309 dB
    half = zeros.copy()
    half[:, :16] = 0.5
    assert psnr(zeros, half) == pytest.approx(10.0 * math.log10(8.0), abs=1e-9)
    assert psnr(half, half) == math.inf
    with pytest.raises(ValueError, match="shapes differ"):
        psnr(zeros, np.zeros((8, 8, 3)))


def test_ssim_of_known_pairs():
    a = np.random.default_rng(0).random(SHAPE)
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    # Constant images 0.5 and 0.25: every window has zero variance, so
    # SSIM = (2 * 0.5 * 0.25 + C1) / (0.5^2 + 0.25^2 + C1) * (C2 / C2), C1 = (0.01 * 1)^2 = 1e-4
    #      = 0.2501 / 0.3126 = 0.800064
    expected = (2 * 0.5 * 0.25 + 1e-4) / (0.25 + 0.0625 + 1e-4)
    assert ssim(np.full(SHAPE, 0.5), np.full(SHAPE, 0.25)) == pytest.approx(expected, abs=1e-9)
    assert ssim(a, 1.0 - a) < 0.0  # anti-correlated


def test_cieluv_matches_closed_form_and_reference():
    white, black, red = np.ones(3), np.zeros(3), np.array([1.0, 0.0, 0.0])
    assert np.allclose(srgb_to_luv(white), [100.0, 0.0, 0.0], atol=1e-3)
    assert np.allclose(srgb_to_luv(black), [0.0, 0.0, 0.0], atol=1e-9)
    # sRGB red in CIELUV (D65): L* 53.24, u* 175.0, v* 37.76
    assert np.allclose(srgb_to_luv(red), [53.24, 175.0, 37.76], atol=0.1)
    img = np.random.default_rng(1).random((8, 8, 3))
    assert np.allclose(srgb_to_luv(img), rgb2luv(img), atol=0.05)


def test_cieluv_difference_zero_for_identical_symmetric_and_known():
    rng = np.random.default_rng(2)
    a, b = rng.random((16, 16, 3)), rng.random((16, 16, 3))
    assert np.array_equal(luv_difference(a, a), np.zeros((16, 16)))
    assert np.array_equal(luv_difference(a, b), luv_difference(b, a))
    assert (luv_difference(a, b) > 0).all()
    # black against white: only L* differs, by 100
    assert np.allclose(luv_difference(np.zeros((2, 2, 3)), np.ones((2, 2, 3))), 100.0, atol=1e-3)


def test_difference_legend_is_fixed():
    delta = np.array([[0.0, DIFFERENCE_SCALE_MAX, 10 * DIFFERENCE_SCALE_MAX]])
    img = colourize_difference(delta)
    assert img.dtype == np.uint8 and img.shape == (1, 3, 3)
    assert img[0, 0].tolist() == [255, 255, 255]  # no difference: white
    assert img[0, 1].tolist() == img[0, 2].tolist()  # above the scale: the top colour
    assert np.allclose(legend_colours(np.array([1.0])), legend_colours(np.array([5.0])))
    with pytest.raises(ValueError, match="positive"):
        colourize_difference(delta, 0.0)


def test_pareto_front_by_hand():
    # (ms, psnr): (1, 10) fastest; (2, 20) best; (3, 15) and (2, 19) are dominated by (2, 20)
    assert pareto_front([1.0, 2.0, 3.0, 2.0], [10.0, 20.0, 15.0, 19.0]) == [True, True, False, False]


def test_placement_on_the_papers_test_path():
    scene_axes = (SceneAxis("om", 0.12, 0.155, 3), SceneAxis("ob", 0.0215, 0.0235, 3), SceneAxis("h", 0.55, 0.85, 5))
    axes = tuple(ParamAxis(a.name, a.low, a.high, a.values(), a.values()[1]) for a in scene_axes)
    placements = classify(axes, np.asarray(path_params(scene_axes, 181)))
    motions = [p.motion for p in placements]
    assert motions.count("one") == 90 and motions.count("all") == 91  # the paper's 90 + 91 frames
    assert not any(p.at_training_values for p in placements)
    assert all(0.25 - 1e-9 <= p.offset <= 0.5 for p in placements)
    at_knots = classify(axes, np.array([[0.12, 0.0225, 0.85], [0.12, 0.0225, 0.85]]))
    assert all(p.at_training_values and p.offset == 0.0 and p.motion == "none" for p in at_knots)


def test_spacing_offset_by_hand():
    axis = ParamAxis("t", 0.0, 1.0, (0.0, 0.5, 1.0), 0.5)
    assert spacing_offset(axis, 0.5) == 0.0
    assert spacing_offset(axis, 0.25) == pytest.approx(0.5)  # midway
    assert spacing_offset(axis, 0.625) == pytest.approx(0.25)


def test_json_safe_writes_strict_json():
    assert json_safe({"a": [math.inf, math.nan, 1.5], "b": (2,)}) == {"a": ["inf", None, 1.5], "b": [2]}
