// Interpolation primitives for camera paths, a mirror of model/visnerf/animation/splines.py:
// orbit angles to and from view directions, slerp and a spherical Catmull-Rom (Barry-Goldman) for
// directions, piecewise-linear and monotone cubic (PCHIP) interpolation for scalars. Plain
// numbers and 3-arrays; nothing here knows about keyframes.

const DEG = Math.PI / 180;

/** Unit direction from the orbit target to the camera. */
export function anglesToDirection(azimuthDeg, elevationDeg) {
  const az = azimuthDeg * DEG;
  const el = elevationDeg * DEG;
  return [Math.cos(el) * Math.sin(az), Math.sin(el), Math.cos(el) * Math.cos(az)];
}

/** (azimuth, elevation) in degrees of a unit direction; azimuth in [-180, 180]. */
export function directionToAngles([x, y, z]) {
  const azimuth = Math.atan2(x, z) / DEG;
  const elevation = Math.asin(Math.max(-1, Math.min(1, y))) / DEG;
  return { azimuth: Object.is(azimuth, -0) ? 0 : azimuth, elevation };
}

const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const scale = (a, k) => [a[0] * k, a[1] * k, a[2] * k];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const norm = (a) => Math.hypot(a[0], a[1], a[2]);
export const unit = (a) => scale(a, 1 / norm(a));

/** Angle in radians between unit vectors. */
export function angleBetween(a, b) {
  return Math.acos(Math.max(-1, Math.min(1, dot(a, b))));
}

/** A unit vector perpendicular to unit `a` (a fixed choice, for the antipodal case). */
function perpendicular(a) {
  return unit(cross(a, Math.abs(a[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0]));
}

/**
 * Spherical linear interpolation of unit vectors: `a` turned by `u` times the angle between them
 * about their common normal (the shortest way; `u` outside [0, 1] goes on along the great circle).
 */
export function slerp(a, b, u) {
  const theta = angleBetween(a, b);
  if (theta < 1e-12) return [...a];
  const axisRaw = cross(a, b);
  const n = norm(axisRaw);
  const axis = n < 1e-12 ? perpendicular(a) : scale(axisRaw, 1 / n);
  const angle = u * theta;
  return unit(add(scale(a, Math.cos(angle)), scale(cross(axis, a), Math.sin(angle))));
}

/**
 * The Catmull-Rom spline through points[1] (at knots[1]) and points[2] (at knots[2]), at `t`, by
 * the Barry-Goldman pyramid of `mix` steps (slerp here: every step stays on the sphere).
 */
export function catmullRom([p0, p1, p2, p3], [t0, t1, t2, t3], t, mix) {
  const a1 = mix(p0, p1, (t - t0) / (t1 - t0));
  const a2 = mix(p1, p2, (t - t1) / (t2 - t1));
  const a3 = mix(p2, p3, (t - t2) / (t3 - t2));
  const b1 = mix(a1, a2, (t - t0) / (t2 - t0));
  const b2 = mix(a2, a3, (t - t1) / (t3 - t1));
  return mix(b1, b2, (t - t1) / (t2 - t1));
}

/** Index of the last x[i] <= t (Python's bisect_right - 1), clamped to [0, n - 1]. */
export function segmentOf(x, t) {
  let k = 0;
  while (k + 1 < x.length && x[k + 1] <= t) k += 1;
  return k;
}

/** Piecewise-linear interpolation, held at the end values (numpy's interp). */
export function interp(x, y, t) {
  if (x.length === 1 || t <= x[0]) return y[0];
  if (t >= x[x.length - 1]) return y[y.length - 1];
  const k = segmentOf(x, t);
  return y[k] + ((t - x[k]) / (x[k + 1] - x[k])) * (y[k + 1] - y[k]);
}

function pchipEnd(h0, h1, m0, m1) {
  const d = ((2 * h0 + h1) * m0 - h0 * m1) / (h0 + h1);
  if (Math.sign(d) !== Math.sign(m0)) return 0;
  if (Math.sign(m0) !== Math.sign(m1) && Math.abs(d) > 3 * Math.abs(m0)) return 3 * m0;
  return d;
}

/** Knot slopes of the monotone cubic (Fritsch-Butland; scipy's PchipInterpolator). */
function pchipSlopes(x, y) {
  const n = x.length;
  const h = x.slice(1).map((xi, i) => xi - x[i]);
  const m = h.map((hi, i) => (y[i + 1] - y[i]) / hi);
  if (n === 2) return [m[0], m[0]];
  const d = new Array(n).fill(0);
  for (let i = 1; i < n - 1; i += 1) {
    const flat = Math.sign(m[i]) !== Math.sign(m[i - 1]) || m[i] === 0 || m[i - 1] === 0;
    const w1 = 2 * h[i] + h[i - 1];
    const w2 = h[i] + 2 * h[i - 1];
    d[i] = flat ? 0 : (w1 + w2) / (w1 / m[i - 1] + w2 / m[i]);
  }
  d[0] = pchipEnd(h[0], h[1], m[0], m[1]);
  d[n - 1] = pchipEnd(h[n - 2], h[n - 3], m[n - 2], m[n - 3]);
  return d;
}

/** The monotone cubic through (x, y) at `t` (held at the end values): never overshoots. */
export function pchip(x, y, t) {
  if (x.length === 1 || t <= x[0]) return y[0];
  if (t >= x[x.length - 1]) return y[y.length - 1];
  const d = pchipSlopes(x, y);
  const k = segmentOf(x, t);
  const h = x[k + 1] - x[k];
  const s = (t - x[k]) / h;
  const h00 = 2 * s ** 3 - 3 * s ** 2 + 1;
  const h10 = s ** 3 - 2 * s ** 2 + s;
  const h01 = -2 * s ** 3 + 3 * s ** 2;
  const h11 = s ** 3 - s ** 2;
  return h00 * y[k] + h10 * h * d[k] + h01 * y[k + 1] + h11 * h * d[k + 1];
}
