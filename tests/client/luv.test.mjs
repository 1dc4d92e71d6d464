// Unit checks of client/js/luv.js: run with `node --test tests/client/`.
// Reference values from scikit-image 0.26 `skimage.color.rgb2luv` (same matrix, D65 white).
import assert from "node:assert/strict";
import { test } from "node:test";

import {
  colourizeDelta,
  deltaEuv,
  legendColour,
  LEGEND_STOPS,
  percentile,
  srgb8ToLuv,
  srgbToLinear,
} from "../../client/js/luv.js";

const close = (actual, expected, tol, what) =>
  assert.ok(Math.abs(actual - expected) <= tol, `${what}: ${actual} vs ${expected} (tol ${tol})`);

test("sRGB transfer curve: linear segment, knee and endpoints", () => {
  close(srgbToLinear(0), 0, 1e-12, "black");
  close(srgbToLinear(1), 1, 1e-12, "white");
  close(srgbToLinear(0.04045), 0.04045 / 12.92, 1e-12, "knee");
  // 0.5 -> ((0.5 + 0.055) / 1.055) ^ 2.4 = 0.21404
  close(srgbToLinear(0.5), 0.21404, 1e-5, "mid grey");
});

test("8-bit sRGB to CIELUV matches scikit-image", () => {
  const cases = [
    [[255, 255, 255], [100.0, 0.0, 0.0]],
    [[255, 0, 0], [53.2406, 175.0145, 37.7562]],
    [[0, 255, 0], [87.7351, -83.0779, 107.3991]],
    [[0, 0, 255], [32.2957, -9.4049, -130.337]],
    [[128, 128, 128], [53.585, 0.0, 0.0]],
    [[10, 20, 30], [5.9485, -2.256, -4.5129]],
    [[200, 100, 50], [53.6295, 80.0896, 39.8906]],
    [[0, 0, 0], [0, 0, 0]],
  ];
  for (const [rgb, luv] of cases) {
    const got = srgb8ToLuv(...rgb);
    ["L*", "u*", "v*"].forEach((name, k) => close(got[k], luv[k], 0.02, `${rgb} ${name}`));
  }
});

test("dE*uv of identical images is zero and of black vs white is 100", () => {
  const a = new Uint8ClampedArray([0, 0, 0, 255, 255, 255, 255, 255]);
  const same = deltaEuv(a, a);
  assert.equal(same.max, 0);
  assert.equal(same.mean, 0);
  const b = new Uint8ClampedArray([255, 255, 255, 255, 0, 0, 0, 255]);
  const diff = deltaEuv(a, b);
  // white is L* = 100 with u* = v* ~ 0; black is (0, 0, 0): distance 100.
  close(diff.delta[0], 100, 0.02, "black vs white");
  close(diff.delta[1], 100, 0.02, "white vs black");
  close(diff.mean, 100, 0.02, "mean");
});

test("red vs green distance equals the Euclidean distance of their L*u*v*", () => {
  const red = new Uint8ClampedArray([255, 0, 0, 255]);
  const green = new Uint8ClampedArray([0, 255, 0, 255]);
  const expected = Math.hypot(53.2406 - 87.7351, 175.0145 + 83.0779, 37.7562 - 107.3991);
  close(deltaEuv(red, green).delta[0], expected, 0.05, "red vs green");
});

test("different sizes are refused", () => {
  assert.throws(() => deltaEuv(new Uint8ClampedArray(4), new Uint8ClampedArray(8)), /sizes differ/);
});

test("legend: endpoints, clamping and monotone lightness", () => {
  assert.deepEqual(legendColour(0), LEGEND_STOPS[0].slice(1));
  assert.deepEqual(legendColour(1), LEGEND_STOPS.at(-1).slice(1));
  assert.deepEqual(legendColour(-3), legendColour(0));
  assert.deepEqual(legendColour(7), legendColour(1));
  let previous = -1;
  for (let t = 0; t <= 1.0001; t += 0.05) {
    const l = srgb8ToLuv(...legendColour(t))[0];
    assert.ok(l > previous, `legend lightness must increase (t=${t.toFixed(2)})`);
    previous = l;
  }
});

test("colourizeDelta maps 0 and >= scale to the legend ends", () => {
  const rgba = colourizeDelta(new Float32Array([0, 10, 1000]), 10);
  assert.deepEqual(Array.from(rgba.slice(0, 4)), [...legendColour(0), 255]);
  assert.deepEqual(Array.from(rgba.slice(4, 8)), [...legendColour(1), 255]);
  assert.deepEqual(Array.from(rgba.slice(8, 12)), [...legendColour(1), 255]);
});

test("percentile uses nearest rank", () => {
  assert.equal(percentile(new Float32Array([1, 2, 3, 4]), 0.5), 2);
  assert.equal(percentile(new Float32Array([5]), 0.95), 5);
  assert.equal(percentile([], 0.5), 0);
});
