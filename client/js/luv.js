// CIELUV colour difference between two images, and the fixed colour legend that shows it.
//
// Pure functions on numbers and typed arrays: no DOM, so `node --test` can check them
// (tests/client/luv.test.mjs).
//
// Pipeline per pixel: 8-bit sRGB -> linear RGB (IEC 61966-2-1 transfer curve) -> CIE XYZ
// (sRGB primaries, D65 white, Y of white = 1) -> CIE 1976 L*u*v* -> Euclidean distance
// dE*uv = sqrt(dL^2 + du^2 + dv^2).

/** sRGB -> XYZ matrix (sRGB primaries, D65), rows X, Y, Z. Same figures as scikit-image. */
export const XYZ_FROM_LINEAR_RGB = [
  [0.412453, 0.35758, 0.180423],
  [0.212671, 0.71516, 0.072169],
  [0.019334, 0.119193, 0.950227],
];

/** D65 reference white (2 degree observer), Y normalised to 1. */
export const WHITE_D65 = [0.95047, 1.0, 1.08883];

const EPSILON = 216 / 24389; // (6/29)^3
const KAPPA = 24389 / 27; // (29/3)^3
const WHITE_DENOM = WHITE_D65[0] + 15 * WHITE_D65[1] + 3 * WHITE_D65[2];
const U_PRIME_WHITE = (4 * WHITE_D65[0]) / WHITE_DENOM;
const V_PRIME_WHITE = (9 * WHITE_D65[1]) / WHITE_DENOM;

/** Decode one sRGB channel in [0, 1] to linear light in [0, 1]. */
export function srgbToLinear(c) {
  return c <= 0.04045 ? c / 12.92 : Math.pow((c + 0.055) / 1.055, 2.4);
}

/** Linear RGB (each in [0, 1]) -> [X, Y, Z]. */
export function linearRgbToXyz(r, g, b) {
  const m = XYZ_FROM_LINEAR_RGB;
  return [
    m[0][0] * r + m[0][1] * g + m[0][2] * b,
    m[1][0] * r + m[1][1] * g + m[1][2] * b,
    m[2][0] * r + m[2][1] * g + m[2][2] * b,
  ];
}

/** [X, Y, Z] -> [L*, u*, v*] relative to the D65 white. Black (X+15Y+3Z = 0) maps to [0, 0, 0]. */
export function xyzToLuv(x, y, z) {
  const yr = y / WHITE_D65[1];
  const l = yr > EPSILON ? 116 * Math.cbrt(yr) - 16 : KAPPA * yr;
  const denom = x + 15 * y + 3 * z;
  if (denom <= 0) return [0, 0, 0];
  const uPrime = (4 * x) / denom;
  const vPrime = (9 * y) / denom;
  return [l, 13 * l * (uPrime - U_PRIME_WHITE), 13 * l * (vPrime - V_PRIME_WHITE)];
}

/** 8-bit sRGB (0..255 each) -> [L*, u*, v*]. */
export function srgb8ToLuv(r, g, b) {
  const [x, y, z] = linearRgbToXyz(srgbToLinear(r / 255), srgbToLinear(g / 255), srgbToLinear(b / 255));
  return xyzToLuv(x, y, z);
}

// 8-bit decode table: the transfer curve is evaluated 256 times, not once per pixel.
const LINEAR_FROM_SRGB8 = new Float64Array(256);
for (let i = 0; i < 256; i += 1) LINEAR_FROM_SRGB8[i] = srgbToLinear(i / 255);

/**
 * L*u*v* of every pixel of an RGBA8 buffer (alpha ignored).
 * @param {Uint8ClampedArray|Uint8Array} rgba length 4 * n
 * @returns {Float32Array} length 3 * n, interleaved L, u, v
 */
export function rgbaToLuv(rgba) {
  const n = rgba.length >> 2;
  const out = new Float32Array(3 * n);
  const m = XYZ_FROM_LINEAR_RGB;
  for (let i = 0; i < n; i += 1) {
    const r = LINEAR_FROM_SRGB8[rgba[4 * i]];
    const g = LINEAR_FROM_SRGB8[rgba[4 * i + 1]];
    const b = LINEAR_FROM_SRGB8[rgba[4 * i + 2]];
    const x = m[0][0] * r + m[0][1] * g + m[0][2] * b;
    const y = m[1][0] * r + m[1][1] * g + m[1][2] * b;
    const z = m[2][0] * r + m[2][1] * g + m[2][2] * b;
    const luv = xyzToLuv(x, y, z);
    out[3 * i] = luv[0];
    out[3 * i + 1] = luv[1];
    out[3 * i + 2] = luv[2];
  }
  return out;
}

/**
 * Per-pixel CIELUV distance dE*uv between two RGBA8 images of the same size.
 * @returns {{delta: Float32Array, mean: number, max: number, p95: number}}
 */
export function deltaEuv(rgbaA, rgbaB) {
  if (rgbaA.length !== rgbaB.length) {
    throw new Error(`image sizes differ (${rgbaA.length / 4} vs ${rgbaB.length / 4} pixels)`);
  }
  const luvA = rgbaToLuv(rgbaA);
  const luvB = rgbaToLuv(rgbaB);
  const n = rgbaA.length >> 2;
  const delta = new Float32Array(n);
  let sum = 0;
  let max = 0;
  for (let i = 0; i < n; i += 1) {
    const dl = luvA[3 * i] - luvB[3 * i];
    const du = luvA[3 * i + 1] - luvB[3 * i + 1];
    const dv = luvA[3 * i + 2] - luvB[3 * i + 2];
    const d = Math.sqrt(dl * dl + du * du + dv * dv);
    delta[i] = d;
    sum += d;
    if (d > max) max = d;
  }
  return { delta, mean: n ? sum / n : 0, max, p95: percentile(delta, 0.95) };
}

/** The q-quantile (0..1) of an array of numbers (nearest rank); 0 for an empty array. */
export function percentile(values, q) {
  if (!values.length) return 0;
  const sorted = Float32Array.from(values).sort();
  const rank = Math.min(sorted.length - 1, Math.max(0, Math.ceil(q * sorted.length) - 1));
  return sorted[rank];
}

/**
 * The legend's colour map (inferno-like, perceptually ordered, dark = no difference), as
 * control points [position in 0..1, r, g, b]. Fixed, so the same colour always means the
 * same dE*uv for a given scale.
 */
export const LEGEND_STOPS = [
  [0.0, 0, 0, 4],
  [0.125, 31, 12, 72],
  [0.25, 85, 15, 109],
  [0.375, 136, 34, 106],
  [0.5, 186, 54, 85],
  [0.625, 227, 89, 51],
  [0.75, 249, 140, 10],
  [0.875, 249, 201, 50],
  [1.0, 252, 255, 164],
];

/** [r, g, b] (0..255) of the legend at t in [0, 1] (clamped). */
export function legendColour(t) {
  const x = Math.min(1, Math.max(0, Number.isFinite(t) ? t : 0));
  for (let k = 1; k < LEGEND_STOPS.length; k += 1) {
    const [p1, r1, g1, b1] = LEGEND_STOPS[k];
    if (x <= p1) {
      const [p0, r0, g0, b0] = LEGEND_STOPS[k - 1];
      const w = (x - p0) / (p1 - p0);
      return [
        Math.round(r0 + w * (r1 - r0)),
        Math.round(g0 + w * (g1 - g0)),
        Math.round(b0 + w * (b1 - b0)),
      ];
    }
  }
  const last = LEGEND_STOPS[LEGEND_STOPS.length - 1];
  return [last[1], last[2], last[3]];
}

const LEGEND_LUT = (() => {
  const lut = new Uint8Array(256 * 3);
  for (let i = 0; i < 256; i += 1) lut.set(legendColour(i / 255), 3 * i);
  return lut;
})();

/**
 * Colour a dE*uv field through the legend: 0 -> first colour, >= scaleMax -> last colour.
 * @param {Float32Array} delta length n
 * @param {number} scaleMax dE*uv at the top of the legend
 * @returns {Uint8ClampedArray} RGBA8, length 4 * n, opaque
 */
export function colourizeDelta(delta, scaleMax) {
  const out = new Uint8ClampedArray(delta.length * 4);
  const k = 255 / Math.max(scaleMax, 1e-6);
  for (let i = 0; i < delta.length; i += 1) {
    const idx = Math.min(255, Math.max(0, Math.round(delta[i] * k)));
    out[4 * i] = LEGEND_LUT[3 * idx];
    out[4 * i + 1] = LEGEND_LUT[3 * idx + 1];
    out[4 * i + 2] = LEGEND_LUT[3 * idx + 2];
    out[4 * i + 3] = 255;
  }
  return out;
}
