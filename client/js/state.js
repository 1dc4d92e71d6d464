// The view state: scene, camera and parameter values (A, and B for comparison), the movie's camera
// path, with clamping to the ranges the server declared, change notification, and
// (de)serialisation to the page URL.

import { emptyPath, PathError, pathFromQuery, pathToQueryEntries } from "./path.js";

export const ELEVATION_LIMIT = 89.9;
/** Zoom range, as multiples of the scene's default camera distance (orthographic: view height). */
export const DISTANCE_RANGE = [0.3, 4.0];
export const PROJECTIONS = ["perspective", "orthographic"];

/** Wrap an angle in degrees into [-180, 180). */
export function wrapAzimuth(deg) {
  const wrapped = ((((deg + 180) % 360) + 360) % 360) - 180;
  return Object.is(wrapped, -0) ? 0 : wrapped;
}

export function clamp(value, lo, hi) {
  return Math.min(hi, Math.max(lo, value));
}

/** Round for display and URLs: enough digits to restore the view, no float noise. */
export function roundTo(value, digits = 4) {
  const k = 10 ** digits;
  return Math.round(value * k) / k;
}

// Keys of the URL that are not parameter names.
const RESERVED = new Set(["scene", "az", "el", "dist", "fov", "proj", "vh", "res", "cmp", "kf", "kfi"]);
const B_PREFIX = "b.";

export class ViewState extends EventTarget {
  constructor() {
    super();
    this.scene = null; // the scene description from GET /api/scenes/{id}
    this.camera = { azimuth: 0, elevation: 0, distance: 1 };
    this.fovDeg = 30; // the perspective lens
    this.projection = "perspective";
    this.viewHeight = 1; // the orthographic lens: world units the view spans vertically
    this.params = {}; // A
    this.paramsB = {}; // B (comparison)
    this.compare = false;
    this.resolution = 256; // long side of a full-quality frame, in pixels
    this.fitScreen = true; // after that frame, one at the size the view is shown (screenSize)
    this.path = emptyPath(); // the movie's keyframes (path.js document)
    this.pathWarning = null; // why the path of the last applied URL was left out, or null
  }

  get sceneId() {
    return this.scene ? this.scene.id : null;
  }

  get defaultCamera() {
    const c = (this.scene && this.scene.camera) || {};
    return {
      azimuth: Number.isFinite(c.azimuth) ? c.azimuth : 0,
      elevation: Number.isFinite(c.elevation) ? c.elevation : 20,
      distance: Number.isFinite(c.distance) && c.distance > 0 ? c.distance : 4,
    };
  }

  /** The scene's default camera as a path keyframe's fallback: azimuth, elevation, distance, fov
   * (and view_height, for a scene of orthographic images). */
  get sceneCamera() {
    const out = { ...this.defaultCamera, fov: this.sceneFov };
    if (this.sceneProjection === "orthographic") out.view_height = this.sceneViewHeight;
    return out;
  }

  /** The projection of the training images, which the view starts in. */
  get sceneProjection() {
    return this.scene && this.scene.camera.projection === "orthographic" ? "orthographic" : "perspective";
  }

  get sceneFov() {
    const fov = this.scene && this.scene.camera.fov_deg;
    return Number.isFinite(fov) && fov > 0 && fov < 180 ? fov : 30;
  }

  /** The scene's view height; for a perspective scene the one framing it alike at the default distance. */
  get sceneViewHeight() {
    const h = this.scene && this.scene.camera.view_height;
    if (Number.isFinite(h) && h > 0) return h;
    return 2 * this.defaultCamera.distance * Math.tan((this.sceneFov * Math.PI) / 360);
  }

  get distanceRange() {
    const d = this.defaultCamera.distance;
    return [d * DISTANCE_RANGE[0], d * DISTANCE_RANGE[1]];
  }

  get viewHeightRange() {
    const h = this.sceneViewHeight;
    return [h * DISTANCE_RANGE[0], h * DISTANCE_RANGE[1]];
  }

  /** The lens of a render request: {projection, fovDeg, viewHeight}, the other projection's null. */
  lens() {
    if (this.projection === "orthographic") return { projection: "orthographic", fovDeg: null, viewHeight: this.viewHeight };
    return { projection: "perspective", fovDeg: this.fovDeg, viewHeight: null };
  }

  /** The view's camera as a path keyframe holds it: fov, or view_height when orthographic. */
  keyframeCamera() {
    const lens = this.projection === "orthographic" ? { view_height: this.viewHeight } : { fov: this.fovDeg };
    return { ...this.camera, ...lens };
  }

  /** Show a keyframe's camera (fov or view_height; the projection follows). */
  applyKeyframeCamera(camera, options) {
    const projection = Number.isFinite(camera.view_height) ? "orthographic" : "perspective";
    const switched = projection !== this.projection;
    this.projection = projection;
    const { azimuth, elevation, distance } = camera;
    this.setCamera({ azimuth, elevation, distance }, options);
    if (projection === "orthographic") this.setViewHeight(camera.view_height, options);
    else this.setFov(camera.fov, options);
    if (switched) this.emit("camera", { interactive: false, ...options });
  }

  axis(name) {
    return this.scene ? this.scene.params.find((a) => a.name === name) : undefined;
  }

  /** Default parameter values of a scene (the declared default, else the range middle). */
  defaultParams() {
    const out = {};
    for (const axis of this.scene ? this.scene.params : []) out[axis.name] = axisDefault(axis);
    return out;
  }

  /** Switch to a scene: camera, parameters and B reset to the scene's defaults. */
  setScene(scene) {
    this.scene = normalizeScene(scene);
    this.camera = this.defaultCamera;
    this.fovDeg = this.sceneFov;
    this.projection = this.sceneProjection;
    this.viewHeight = this.sceneViewHeight;
    this.params = this.defaultParams();
    this.paramsB = this.defaultParams();
    this.path = emptyPath();
    this.pathWarning = null;
    this.emit("scene", { interactive: false });
  }

  /** Change the camera (partial), wrapped and clamped. */
  setCamera(partial, { interactive = true, inputTime } = {}) {
    const [dMin, dMax] = this.distanceRange;
    const next = { ...this.camera, ...partial };
    next.azimuth = wrapAzimuth(next.azimuth);
    next.elevation = clamp(next.elevation, -ELEVATION_LIMIT, ELEVATION_LIMIT);
    next.distance = clamp(next.distance, dMin, dMax);
    const c = this.camera;
    if (next.azimuth === c.azimuth && next.elevation === c.elevation && next.distance === c.distance) return;
    this.camera = next;
    this.emit("camera", { interactive, inputTime });
  }

  /** Change the field of view (degrees, within (0, 180)). */
  setFov(deg, { interactive = true, inputTime } = {}) {
    if (!Number.isFinite(deg) || deg <= 0 || deg >= 180 || deg === this.fovDeg) return;
    this.fovDeg = deg;
    this.emit("camera", { interactive, inputTime });
  }

  /** Change the orthographic view height (world units, clamped to the zoom range). */
  setViewHeight(height, { interactive = true, inputTime } = {}) {
    if (!Number.isFinite(height) || height <= 0) return;
    const [lo, hi] = this.viewHeightRange;
    const next = clamp(height, lo, hi);
    if (next === this.viewHeight) return;
    this.viewHeight = next;
    this.emit("camera", { interactive, inputTime });
  }

  /** Switch between perspective and orthographic, keeping the framing of the orbit centre
   * (view height = 2 d tan(fov / 2), as the server's lens rule has it). */
  setProjection(projection, { interactive = false, inputTime } = {}) {
    if (!PROJECTIONS.includes(projection) || projection === this.projection) return;
    const halfTan = Math.tan((this.fovDeg * Math.PI) / 360);
    if (projection === "orthographic") {
      const [lo, hi] = this.viewHeightRange;
      this.viewHeight = clamp(2 * this.camera.distance * halfTan, lo, hi);
    } else {
      const [lo, hi] = this.distanceRange;
      this.camera = { ...this.camera, distance: clamp(this.viewHeight / (2 * halfTan), lo, hi) };
    }
    this.projection = projection;
    this.emit("camera", { interactive, inputTime });
  }

  orbit(dAzimuth, dElevation, options) {
    this.setCamera(
      { azimuth: this.camera.azimuth + dAzimuth, elevation: this.camera.elevation + dElevation },
      options,
    );
  }

  /** Zoom: the camera distance, or the view height of an orthographic view (whose image does not
   * change with distance). */
  zoom(factor, options) {
    if (this.projection === "orthographic") this.setViewHeight(this.viewHeight * factor, options);
    else this.setCamera({ distance: this.camera.distance * factor }, options);
  }

  /** Back to the scene's default camera and lens. */
  resetCamera() {
    this.camera = this.defaultCamera;
    this.fovDeg = this.sceneFov;
    this.projection = this.sceneProjection;
    this.viewHeight = this.sceneViewHeight;
    this.emit("camera", { interactive: false });
  }

  /** Set one parameter of set "A" or "B", clamped to its range. Returns the stored value. */
  setParam(name, value, { set = "A", interactive = true, inputTime } = {}) {
    const axis = this.axis(name);
    if (!axis || !Number.isFinite(value)) return undefined;
    const target = set === "B" ? this.paramsB : this.params;
    const v = clamp(value, axis.min, axis.max);
    if (target[name] === v) return v;
    target[name] = v;
    this.emit(set === "B" ? "paramsB" : "params", { interactive, inputTime, name });
    return v;
  }

  pinAsB() {
    this.paramsB = { ...this.params };
    this.emit("paramsB", { interactive: false });
  }

  setCompare(on) {
    if (this.compare === on) return;
    this.compare = on;
    this.emit("compare", { interactive: false });
  }

  /** Replace the movie's camera path (a path.js document). */
  setPath(path) {
    this.path = path;
    this.emit("path", { interactive: false });
  }

  /** Full frames of this long side alone (no frame at the view's size after them). */
  setResolution(px) {
    this.chooseResolution(px);
  }

  /** The Resolution menu: "screen" (a full frame at ``resolution``, then one at the view's size),
   * or a long side in pixels alone. */
  chooseResolution(value) {
    const screen = value === "screen";
    const px = screen ? this.resolution : Math.round(Number(value));
    if (!(px >= 16) || (screen === this.fitScreen && px === this.resolution)) return;
    this.fitScreen = screen;
    this.resolution = px;
    this.emit("resolution", { interactive: false });
  }

  /**
   * The frame that fills a view `box` ({width, height} in device pixels) at the training aspect,
   * within the server's `limits` ({max_side, max_full_pixels}); null unless `fitScreen` is on and
   * it is larger than the full-quality frame (`frameSize`), which it then follows when still.
   */
  screenSize(box, limits) {
    if (!this.fitScreen || !(box && box.width > 0 && box.height > 0)) return null;
    const [w, h] = (this.scene && this.scene.image_size) || [1, 1];
    let scale = Math.min(box.width / w, box.height / h);
    if (limits) {
      if (limits.max_side > 0) scale = Math.min(scale, limits.max_side / Math.max(w, h));
      if (limits.max_full_pixels > 0) scale = Math.min(scale, Math.sqrt(limits.max_full_pixels / (w * h)));
    }
    const size = { width: Math.max(16, Math.floor(w * scale)), height: Math.max(16, Math.floor(h * scale)) };
    const full = this.fullSize();
    return Math.max(size.width, size.height) > Math.max(full.width, full.height) ? size : null;
  }

  /**
   * The full-quality frame asked for first when the view is still: the chosen resolution
   * (`frameSize`); with "Fit the view", the training images' size where that is smaller, so the
   * frame at the view's size (`screenSize`) follows sooner (a 128x128 frame of a bundled scene
   * renders in a third of the time of a 256x256 one).
   */
  fullSize() {
    const chosen = this.frameSize();
    if (!this.fitScreen || !this.scene) return chosen;
    const [w, h] = this.scene.image_size;
    return Math.max(w, h) < Math.max(chosen.width, chosen.height) ? { width: w, height: h } : chosen;
  }

  /** Full-quality frame size: the long side is `resolution`, the aspect is the training images'. */
  frameSize(scale = 1) {
    const [w, h] = (this.scene && this.scene.image_size) || [1, 1];
    const long = Math.max(16, Math.round(this.resolution * scale));
    if (w >= h) return { width: long, height: Math.max(16, Math.round((long * h) / w)) };
    return { width: Math.max(16, Math.round((long * w) / h)), height: long };
  }

  emit(type, detail) {
    this.dispatchEvent(new CustomEvent("change", { detail: { type, ...detail } }));
  }

  // ---- URL ---------------------------------------------------------------------------------

  /** The query string that restores this view. */
  toQuery() {
    const q = new URLSearchParams();
    if (!this.scene) return q;
    q.set("scene", this.scene.id);
    q.set("az", String(roundTo(this.camera.azimuth, 2)));
    q.set("el", String(roundTo(this.camera.elevation, 2)));
    q.set("dist", String(roundTo(this.camera.distance, 4)));
    if (this.projection !== this.sceneProjection) q.set("proj", this.projection === "orthographic" ? "o" : "p");
    if (this.projection === "orthographic") q.set("vh", String(roundTo(this.viewHeight, 4)));
    for (const axis of this.scene.params) {
      if (!RESERVED.has(axis.name)) q.set(axis.name, String(roundTo(this.params[axis.name], 6)));
    }
    if (this.compare) {
      q.set("cmp", "1");
      for (const axis of this.scene.params) q.set(B_PREFIX + axis.name, String(roundTo(this.paramsB[axis.name], 6)));
    }
    q.set("res", this.fitScreen ? "screen" : String(this.resolution));
    const names = this.scene.params.map((a) => a.name);
    for (const [key, value] of pathToQueryEntries(this.path, names)) q.append(key, value);
    return q;
  }

  /** Apply what a query string holds for the current scene (unknown keys are ignored). */
  applyQuery(query) {
    const num = (key) => {
      const raw = query.get(key);
      if (raw === null || raw.trim() === "") return undefined;
      const v = Number(raw);
      return Number.isFinite(v) ? v : undefined;
    };
    const [dMin, dMax] = this.distanceRange;
    const camera = { ...this.camera };
    if (num("az") !== undefined) camera.azimuth = wrapAzimuth(num("az"));
    if (num("el") !== undefined) camera.elevation = clamp(num("el"), -ELEVATION_LIMIT, ELEVATION_LIMIT);
    if (num("dist") !== undefined) camera.distance = clamp(num("dist"), dMin, dMax);
    this.camera = camera;
    const proj = { o: "orthographic", p: "perspective" }[query.get("proj")];
    this.projection = proj || this.sceneProjection;
    if (num("vh") !== undefined && num("vh") > 0) {
      const [lo, hi] = this.viewHeightRange;
      this.viewHeight = clamp(num("vh"), lo, hi);
    }
    for (const axis of this.scene ? this.scene.params : []) {
      const a = num(axis.name);
      if (a !== undefined && !RESERVED.has(axis.name)) this.params[axis.name] = clamp(a, axis.min, axis.max);
      const b = num(B_PREFIX + axis.name);
      if (b !== undefined) this.paramsB[axis.name] = clamp(b, axis.min, axis.max);
    }
    if (num("res") !== undefined && num("res") >= 16) {
      this.resolution = Math.round(num("res"));
      this.fitScreen = false;
    } else if (query.get("res") === "screen") this.fitScreen = true;
    this.compare = query.get("cmp") === "1";
    this.path = emptyPath();
    this.pathWarning = null;
    try {
      this.path = pathFromQuery(query, this.scene ? this.scene.params : [], this.sceneCamera) ?? emptyPath();
    } catch (err) {
      if (!(err instanceof PathError)) throw err;
      this.pathWarning = err.message;
    }
    this.emit("restore", { interactive: false });
  }

  /** Write the view into the address bar without adding a history entry. */
  writeUrl() {
    const query = this.toQuery().toString();
    const url = `${location.pathname}${query ? `?${query}` : ""}${location.hash}`;
    if (url !== `${location.pathname}${location.search}${location.hash}`) history.replaceState(null, "", url);
  }
}

export function axisDefault(axis) {
  if (Number.isFinite(axis.default)) return clamp(axis.default, axis.min, axis.max);
  return (axis.min + axis.max) / 2;
}

/**
 * The scene description with the shapes this client works with: `params` a list, `image_size`
 * a [width, height] pair (an object {width, height} is accepted too), `camera` an object.
 */
export function normalizeScene(scene) {
  const out = { ...scene };
  out.params = Array.isArray(scene.params) ? scene.params : [];
  const size = scene.image_size;
  if (Array.isArray(size) && size.length >= 2) out.image_size = [Number(size[0]), Number(size[1])];
  else if (size && typeof size === "object") out.image_size = [Number(size.width), Number(size.height)];
  if (!(out.image_size && out.image_size[0] > 0 && out.image_size[1] > 0)) out.image_size = [256, 256];
  out.camera = scene.camera && typeof scene.camera === "object" ? scene.camera : {};
  return out;
}
