// Camera paths for movies: the path document (version 1, the JSON `visnerf animate` and the movie
// endpoint read), its checks and its sampling, which mirror model/visnerf/animation/parse.py and
// interpolation.py (the primitives are in splines.js), the frame times of a movie, editing, and
// the compact form a path takes in the page URL. Pure functions, no DOM.
//
// Camera conventions (model/visnerf/data/cameras.py): world +y is up; azimuth 0, elevation 0 puts
// the camera on +z; azimuth turns towards +x. The view direction (origin to camera) is
// (cos el sin az, sin el, cos el cos az). The viewer has no roll, so over a pole the preview's
// image turns at once where the server's movie turns it gradually; the directions are the same.

import { anglesToDirection, catmullRom, directionToAngles, interp, pchip, segmentOf, slerp, unit } from "./splines.js";

export const PATH_VERSION = 1;
export const CAMERA_INTERPOLATIONS = ["smooth", "linear"];
export const PARAM_INTERPOLATIONS = ["linear", "smooth"];
/** Most keyframes a path may hold (model/visnerf/animation/keys.py). */
export const MAX_KEYFRAMES = 1000;
/** Seconds between keyframes when a new one is added. */
export const DEFAULT_SPACING_S = 2;

const TOP_LEVEL_KEYS = ["version", "camera_interpolation", "param_interpolation", "keyframes"];
const KEYFRAME_KEYS = ["time", "camera", "params"];
const CAMERA_KEYS = ["azimuth", "elevation", "distance", "fov", "view_height"];
const LENS_KEYS = ["fov", "view_height"];

/** A path that cannot be used; the message names the field, as the server's does
 * (`keyframes[2].camera.elevation: must be in [-90, 90], got 120`). */
export class PathError extends Error {
  constructor(message) {
    super(message);
    this.name = "PathError";
  }
}

// ---- the document (parse.py) ------------------------------------------------------------------

function jsonType(value) {
  if (value === null) return "null";
  if (Array.isArray(value)) return "a list";
  return { object: "an object", string: "a string", boolean: "a boolean" }[typeof value] || typeof value;
}

function isObject(value) {
  return value !== null && typeof value === "object" && !Array.isArray(value);
}

function number(value, where) {
  if (typeof value !== "number") {
    throw new PathError(`${where}: must be a number, got ${jsonType(value)} ${JSON.stringify(value)}`);
  }
  if (!Number.isFinite(value)) throw new PathError(`${where}: must be a finite number, got ${value}`);
  return value;
}

function refuseUnknownKeys(raw, allowed, where) {
  const unknown = Object.keys(raw).filter((k) => !allowed.includes(k)).sort();
  if (unknown.length) {
    const prefix = where === "path" ? "" : `${where}.`;
    throw new PathError(`${prefix}${unknown[0]}: unknown key; allowed: ${allowed.join(", ")}`);
  }
}

/** `value` clamped into the axis range, allowing float32 rounding at the ends; further out: refused. */
function clampToAxis(value, axis, where) {
  const tol = 1e-6 * Math.max(Math.abs(axis.min), Math.abs(axis.max), axis.max - axis.min, 1e-30);
  if (!(axis.min - tol <= value && value <= axis.max + tol)) {
    throw new PathError(`${where}: must be in [${axis.min}, ${axis.max}], got ${value}`);
  }
  return Math.min(Math.max(value, axis.min), axis.max);
}

function axisDefault(axis) {
  return Number.isFinite(axis.default) ? axis.default : (axis.min + axis.max) / 2;
}

/** The projection of a path: that of the first keyframe naming a lens, else the scene's. */
function pathProjection(rawKeys, defaults) {
  for (const kf of rawKeys) {
    const camera = isObject(kf) && isObject(kf.camera) ? kf.camera : {};
    if ("view_height" in camera) return "orthographic";
    if ("fov" in camera) return "perspective";
  }
  return Number.isFinite(defaults.view_height) ? "orthographic" : "perspective";
}

/** The scene's lens in `projection` (visnerf.lens.choose_lens): its own, else the one framing the
 * orbit centre alike from the default distance (view height = 2 d tan(fov / 2)); null for none. */
function defaultLens(defaults, projection) {
  const fov = Number.isFinite(defaults.fov) ? defaults.fov : defaults.fov_deg;
  const height = defaults.view_height;
  const distance = Number.isFinite(defaults.distance) ? defaults.distance : 2;
  if (projection === "orthographic") {
    if (Number.isFinite(height)) return { view_height: height };
    return Number.isFinite(fov) ? { view_height: 2 * distance * Math.tan((fov * Math.PI) / 360) } : {};
  }
  if (Number.isFinite(height)) return { fov: (360 / Math.PI) * Math.atan((0.5 * height) / distance) };
  return Number.isFinite(fov) ? { fov } : {};
}

function readCamera(raw, where, defaults) {
  if (!isObject(raw)) throw new PathError(`${where}: must be a JSON object, got ${jsonType(raw)}`);
  if ("c2w" in raw) {
    throw new PathError(`${where}.c2w: this client reads orbit cameras only (azimuth, elevation, distance, fov)`);
  }
  refuseUnknownKeys(raw, CAMERA_KEYS, where);
  if (LENS_KEYS.every((name) => name in raw)) {
    throw new PathError(`${where}: give fov (perspective) or view_height (orthographic), not both`);
  }
  const lens = LENS_KEYS.find((name) => name in raw) ?? ("view_height" in defaults ? "view_height" : "fov");
  const camera = {};
  for (const name of [...CAMERA_KEYS.slice(0, 3), lens]) {
    if (name in raw) camera[name] = number(raw[name], `${where}.${name}`);
    else if (Number.isFinite(defaults[name])) camera[name] = defaults[name];
    else throw new PathError(`${where}.${name}: missing, and the scene has no default for it`);
  }
  if (!(camera.elevation >= -90 && camera.elevation <= 90)) {
    throw new PathError(`${where}.elevation: must be in [-90, 90], got ${camera.elevation}`);
  }
  if (!(camera.distance > 0)) throw new PathError(`${where}.distance: must be above 0, got ${camera.distance}`);
  if (lens === "fov" && !(camera.fov > 0 && camera.fov < 180)) {
    throw new PathError(`${where}.fov: must be in (0, 180), got ${camera.fov}`);
  }
  if (lens === "view_height" && !(camera.view_height > 0)) {
    throw new PathError(`${where}.view_height: must be above 0, got ${camera.view_height}`);
  }
  return camera;
}

function readParams(raw, where, axes) {
  if (!isObject(raw)) throw new PathError(`${where}: must be a JSON object of name: value, got ${jsonType(raw)}`);
  if (!axes) {
    const out = {};
    for (const [name, value] of Object.entries(raw)) out[name] = number(value, `${where}.${name}`);
    return out;
  }
  const names = axes.map((a) => a.name);
  const unknown = Object.keys(raw).filter((k) => !names.includes(k)).sort();
  if (unknown.length) {
    const has = [...names].sort().join(", ") || "none";
    throw new PathError(`${where}.${unknown[0]}: unknown parameter; this scene has ${has}`);
  }
  const out = {};
  for (const axis of axes) {
    const at = `${where}.${axis.name}`;
    out[axis.name] = axis.name in raw ? clampToAxis(number(raw[axis.name], at), axis, at) : axisDefault(axis);
  }
  return out;
}

/**
 * Check a path document as the server does and return a clean copy. With `axes` ([{name, min,
 * max, default}]) every keyframe names every axis (a missing one takes the axis default) and
 * values outside a range are refused; camera fields left out take `cameraDefaults` (the scene's
 * camera: azimuth, elevation, distance, fov_deg, and view_height for an orthographic scene). The
 * path keeps one projection: that of its first keyframe naming a lens (fov or view_height), else
 * the scene's. Throws PathError naming the field.
 */
export function normalizePath(doc, axes = null, cameraDefaults = {}) {
  if (!isObject(doc)) throw new PathError(`path: must be a JSON object, got ${jsonType(doc)}`);
  refuseUnknownKeys(doc, TOP_LEVEL_KEYS, "path");
  if (!("version" in doc)) throw new PathError(`version: missing (this reader takes version ${PATH_VERSION})`);
  if (doc.version !== PATH_VERSION) {
    throw new PathError(`version: must be ${PATH_VERSION}, got ${JSON.stringify(doc.version)}`);
  }
  const cameraInterpolation = doc.camera_interpolation ?? "smooth";
  const paramInterpolation = doc.param_interpolation ?? "linear";
  if (!CAMERA_INTERPOLATIONS.includes(cameraInterpolation)) {
    throw new PathError(
      `camera_interpolation: must be one of ${CAMERA_INTERPOLATIONS.join(", ")}, got ${JSON.stringify(cameraInterpolation)}`,
    );
  }
  if (!PARAM_INTERPOLATIONS.includes(paramInterpolation)) {
    throw new PathError(
      `param_interpolation: must be one of ${PARAM_INTERPOLATIONS.join(", ")}, got ${JSON.stringify(paramInterpolation)}`,
    );
  }
  const raw = doc.keyframes;
  if (!Array.isArray(raw)) throw new PathError(`keyframes: must be a list of keyframes, got ${jsonType(raw)}`);
  if (!raw.length) throw new PathError("keyframes: must hold at least one keyframe");
  if (raw.length > MAX_KEYFRAMES) {
    throw new PathError(`keyframes: at most ${MAX_KEYFRAMES} keyframes, got ${raw.length}`);
  }
  const projection = pathProjection(raw, cameraDefaults);
  const defaults = { ...cameraDefaults, ...defaultLens(cameraDefaults, projection) };
  delete defaults[projection === "orthographic" ? "fov" : "view_height"];
  const keyframes = raw.map((kf, i) => {
    const where = `keyframes[${i}]`;
    if (!isObject(kf)) throw new PathError(`${where}: must be a JSON object, got ${jsonType(kf)}`);
    refuseUnknownKeys(kf, KEYFRAME_KEYS, where);
    if (!("time" in kf)) throw new PathError(`${where}.time: missing`);
    const time = number(kf.time, `${where}.time`);
    if (time < 0) throw new PathError(`${where}.time: must be >= 0, got ${time}`);
    const camera = readCamera(kf.camera ?? {}, `${where}.camera`, defaults);
    return { time, camera, params: readParams(kf.params ?? {}, `${where}.params`, axes) };
  });
  const orthographic = "view_height" in keyframes[0].camera;
  for (let i = 1; i < keyframes.length; i += 1) {
    if (("view_height" in keyframes[i].camera) !== orthographic) {
      const [first, now] = orthographic ? ["view_height", "fov"] : ["fov", "view_height"];
      throw new PathError(`keyframes[${i}].camera.${now}: keyframes[0] has a ${first}; a path keeps one projection`);
    }
    if (!(keyframes[i].time > keyframes[i - 1].time)) {
      const [before, now] = [keyframes[i - 1].time, keyframes[i].time];
      throw new PathError(`keyframes[${i}].time: must be after keyframes[${i - 1}].time (${before}), got ${now}`);
    }
  }
  return {
    version: PATH_VERSION,
    camera_interpolation: cameraInterpolation,
    param_interpolation: paramInterpolation,
    keyframes,
  };
}

// ---- sampling (interpolation.py) --------------------------------------------------------------

/** Seconds from the first keyframe to the last. */
export function pathDuration(path) {
  const kfs = path.keyframes;
  return kfs.length ? kfs[kfs.length - 1].time - kfs[0].time : 0;
}

/** Python's round(): halves go to the even neighbour. */
function roundHalfEven(x) {
  const r = Math.round(x);
  return Math.abs(x % 1) === 0.5 && r % 2 !== 0 ? r - 1 : r;
}

/** Number of frames of a movie at `fps`: first + i / fps for i = 0 .. round(duration * fps). */
export function frameCount(path, fps) {
  return roundHalfEven(pathDuration(path) * fps) + 1;
}

/** The time (seconds) of every frame of a movie at `fps`, as the server samples them. */
export function frameTimes(path, fps) {
  const first = path.keyframes[0].time;
  return Array.from({ length: frameCount(path, fps) }, (_, i) => first + i / fps);
}

/** The view direction at `t` in segment `k` (between keyframes k and k + 1). */
function directionAt(path, dirs, times, k, t) {
  const [t1, t2] = [times[k], times[k + 1]];
  const [p1, p2] = [dirs[k], dirs[k + 1]];
  if (path.camera_interpolation === "linear") return slerp(p1, p2, (t - t1) / (t2 - t1));
  // A phantom key at either end mirrors its neighbour, as far before (after) as it is after (before).
  const [p0, t0] = k > 0 ? [dirs[k - 1], times[k - 1]] : [slerp(p2, p1, 2), t1 - (t2 - t1)];
  const [p3, t3] = k + 2 < dirs.length ? [dirs[k + 2], times[k + 2]] : [slerp(p1, p2, 2), t2 + (t2 - t1)];
  return unit(catmullRom([p0, p1, p2, p3], [t0, t1, t2, t3], t, slerp));
}

/**
 * The camera at `time` (held at the ends): {azimuth, elevation, distance, and fov or view_height}.
 * Direction by slerp (`linear`) or spherical Catmull-Rom (`smooth`); distance and the lens linear
 * or monotone cubic.
 */
export function cameraAt(path, time) {
  const kfs = path.keyframes;
  const times = kfs.map((k) => k.time);
  const t = Math.min(Math.max(time, times[0]), times[times.length - 1]);
  const k = segmentOf(times, t);
  if (Math.abs(t - times[k]) <= 1e-9 * Math.max(1, Math.abs(t)) || k === kfs.length - 1) return { ...kfs[k].camera };
  const smooth = path.camera_interpolation === "smooth";
  const along = (values) => (smooth ? pchip(times, values, t) : interp(times, values, t));
  const dirs = kfs.map((kf) => anglesToDirection(kf.camera.azimuth, kf.camera.elevation));
  const lens = "view_height" in kfs[0].camera ? "view_height" : "fov";
  return {
    ...directionToAngles(directionAt(path, dirs, times, k, t)),
    distance: along(kfs.map((kf) => kf.camera.distance)),
    [lens]: along(kfs.map((kf) => kf.camera[lens])),
  };
}

/**
 * Every axis' value at `time`: linear or monotone cubic (`smooth`) through the keyframes (a
 * keyframe without the axis counts as its default), clamped to the axis range.
 */
export function paramsAt(path, time, axes) {
  const times = path.keyframes.map((k) => k.time);
  const out = {};
  for (const axis of axes) {
    const values = path.keyframes.map((k) => (axis.name in k.params ? k.params[axis.name] : axisDefault(axis)));
    const value = path.param_interpolation === "smooth" ? pchip(times, values, time) : interp(times, values, time);
    out[axis.name] = Math.min(Math.max(value, axis.min), axis.max);
  }
  return out;
}

// ---- editing ----------------------------------------------------------------------------------

/** A new, empty path (not a valid document until it has a keyframe). */
export function emptyPath() {
  return { version: PATH_VERSION, camera_interpolation: "smooth", param_interpolation: "linear", keyframes: [] };
}

/** The time a keyframe appended now gets: DEFAULT_SPACING_S after the last one. */
export function nextKeyframeTime(path) {
  const kfs = path.keyframes;
  return kfs.length ? kfs[kfs.length - 1].time + DEFAULT_SPACING_S : 0;
}

/** Swap keyframe `index` with its neighbour (`step` -1 or +1); the times stay in their slots. */
export function moveKeyframe(path, index, step) {
  const j = index + step;
  const kfs = path.keyframes.map((k) => ({ ...k }));
  if (index < 0 || index >= kfs.length || j < 0 || j >= kfs.length) return { ...path, keyframes: kfs };
  const [ti, tj] = [kfs[index].time, kfs[j].time];
  [kfs[index], kfs[j]] = [kfs[j], kfs[index]];
  kfs[index].time = ti;
  kfs[j].time = tj;
  return { ...path, keyframes: kfs };
}

/** Give keyframe `index` a new time, re-sorting by time. PathError for a time < 0 or taken. */
export function retimeKeyframe(path, index, time) {
  if (typeof time !== "number" || !Number.isFinite(time) || time < 0) {
    throw new PathError("a keyframe time must be a number of seconds, 0 or more");
  }
  if (path.keyframes.some((k, i) => i !== index && k.time === time)) {
    throw new PathError(`another keyframe is already at ${time} s`);
  }
  const kfs = path.keyframes.map((k, i) => (i === index ? { ...k, time } : { ...k }));
  kfs.sort((x, y) => x.time - y.time);
  return { ...path, keyframes: kfs };
}

/** The path without keyframe `index`. */
export function removeKeyframe(path, index) {
  return { ...path, keyframes: path.keyframes.filter((_, i) => i !== index) };
}

// ---- the URL form -----------------------------------------------------------------------------
//
// One `kf` query key per keyframe, its fields joined by "_" (which URLSearchParams leaves as it
// is): time_azimuth_elevation_distance_lens_p1_p2..., the parameter values in the scene's order;
// the lens is the fov, or "h" and the view height of an orthographic path.
// A `kfi` key holds the interpolations when they are not the defaults: one letter each, camera
// then parameters ("s" smooth, "l" linear), e.g. kfi=ls.

const LETTER = { smooth: "s", linear: "l" };
const FROM_LETTER = { s: "smooth", l: "linear" };

function compact(value, digits) {
  const k = 10 ** digits;
  const r = Math.round(value * k) / k;
  return String(Object.is(r, -0) ? 0 : r);
}

/** The URL entries of a path: [[key, value], ...] (none for an empty path). */
export function pathToQueryEntries(path, paramNames) {
  if (!path || !path.keyframes.length) return [];
  const entries = path.keyframes.map((k) => [
    "kf",
    [
      compact(k.time, 3),
      compact(k.camera.azimuth, 2),
      compact(k.camera.elevation, 2),
      compact(k.camera.distance, 4),
      "view_height" in k.camera ? `h${compact(k.camera.view_height, 4)}` : compact(k.camera.fov, 2),
      ...paramNames.map((name) => (name in k.params ? compact(k.params[name], 6) : "")),
    ].join("_"),
  ]);
  const modes = LETTER[path.camera_interpolation] + LETTER[path.param_interpolation];
  if (modes !== "sl") entries.push(["kfi", modes]);
  return entries;
}

/**
 * The path a URL holds (checked like a document: `axes` and `cameraDefaults` as normalizePath
 * takes them), or null when it holds none. Throws PathError for malformed `kf` entries.
 */
export function pathFromQuery(query, axes, cameraDefaults = {}) {
  const rows = query.getAll("kf");
  if (!rows.length) return null;
  const modes = query.get("kfi") ?? "sl";
  if (modes.length !== 2 || !FROM_LETTER[modes[0]] || !FROM_LETTER[modes[1]]) {
    throw new PathError(`kfi: '${modes}' is not two of the letters s and l`);
  }
  const names = axes.map((a) => a.name);
  const keyframes = rows.map((row, i) => {
    const fields = row.split("_");
    if (fields.length !== 5 + names.length) {
      throw new PathError(`keyframe ${i + 1}: ${fields.length} fields, expected ${5 + names.length}`);
    }
    const value = (j) => (fields[j].trim() === "" ? null : Number(fields[j]));
    const params = {};
    names.forEach((name, j) => {
      if (fields[5 + j] !== "") params[name] = value(5 + j);
    });
    const lens = fields[4].startsWith("h") ? { view_height: Number(fields[4].slice(1)) } : { fov: value(4) };
    return {
      time: value(0),
      camera: { azimuth: value(1), elevation: value(2), distance: value(3), ...lens },
      params,
    };
  });
  const doc = {
    version: PATH_VERSION,
    camera_interpolation: FROM_LETTER[modes[0]],
    param_interpolation: FROM_LETTER[modes[1]],
    keyframes,
  };
  return normalizePath(doc, axes, cameraDefaults);
}
