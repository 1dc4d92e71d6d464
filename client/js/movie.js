// The Movie panel: keyframes on a strip (record, retime, reorder, remove, show), the preview that
// plays the path in the viewer, and saving/loading the path as JSON. The render job lives in
// movie_job.js. The path itself is part of the view state (state.path), so the URL carries it.

import * as api from "./api.js";
import {
  cameraAt,
  frameCount,
  moveKeyframe,
  nextKeyframeTime,
  normalizePath,
  paramsAt,
  pathDuration,
  PathError,
  removeKeyframe,
  retimeKeyframe,
} from "./path.js";
import { ELEVATION_LIMIT, roundTo } from "./state.js";

const THUMB_WIDTH = 72;

/** A small JPEG of what a canvas shows (a data URL), or null when it shows nothing yet. */
function thumbnailOf(canvas) {
  if (!canvas.width || !canvas.height || canvas.classList.contains("empty")) return null;
  const small = document.createElement("canvas");
  small.width = THUMB_WIDTH;
  small.height = Math.max(1, Math.round((THUMB_WIDTH * canvas.height) / canvas.width));
  small.getContext("2d").drawImage(canvas, 0, 0, small.width, small.height);
  return small.toDataURL("image/jpeg", 0.75);
}

/** What a keyframe shows (its camera and parameters, not its time): the key of its thumbnail. */
function viewKey(kf) {
  return JSON.stringify([kf.camera, kf.params]);
}

/** A GET render URL for the thumbnail of a keyframe recorded elsewhere (a link, a file). */
function thumbnailUrl(state, kf) {
  const [w, h] = state.scene.image_size;
  return api.renderUrl(state.sceneId, {
    camera: {
      azimuth: kf.camera.azimuth,
      elevation: Math.max(-ELEVATION_LIMIT, Math.min(ELEVATION_LIMIT, kf.camera.elevation)),
      distance: kf.camera.distance,
    },
    fovDeg: kf.camera.fov,
    viewHeight: kf.camera.view_height,
    width: THUMB_WIDTH,
    height: Math.max(16, Math.round((THUMB_WIDTH * h) / w)),
    params: paramsAt({ ...state.path, keyframes: [kf] }, kf.time, state.scene.params),
    quality: "preview",
    format: "jpeg",
  });
}

/** Plays a path in the viewer in real time, through the view state (so frames are previews). */
class PathPlayer {
  constructor(state, { onStop }) {
    this.state = state;
    this.onStop = onStop;
    this.path = null;
    this.rafId = null;
  }

  get playing() {
    return this.rafId !== null;
  }

  start(path) {
    this.stop();
    this.path = normalizePath(path);
    const startedAt = performance.now();
    const t0 = this.path.keyframes[0].time;
    const end = t0 + pathDuration(this.path);
    const step = (now) => {
      const t = Math.min(end, t0 + Math.max(0, now - startedAt) / 1000);
      this.apply(t, now);
      if (t >= end) this.finish();
      else this.rafId = requestAnimationFrame(step);
    };
    this.rafId = requestAnimationFrame(step);
  }

  apply(time, inputTime) {
    const options = { interactive: true, inputTime };
    this.state.applyKeyframeCamera(cameraAt(this.path, time), options);
    for (const [name, value] of Object.entries(paramsAt(this.path, time, this.state.scene.params))) {
      this.state.setParam(name, value, options);
    }
  }

  finish() {
    this.rafId = null;
    this.onStop();
  }

  stop() {
    if (this.rafId === null) return;
    cancelAnimationFrame(this.rafId);
    this.finish();
  }
}

/**
 * Wire the panel. `el` holds its elements: add, preview, strip, empty, summary, cameraMode,
 * paramMode, save, load, file, and `canvas` (the view whose picture becomes the thumbnail).
 * Returns what the render job needs: {player} (it stops a preview before a render starts) and
 * frameCount(fps), the frames a movie of the current path would have.
 */
export function setupMoviePanel({ state, alerts, el }) {
  const player = new PathPlayer(state, {
    onStop: () => {
      el.preview.textContent = "Preview";
      el.preview.setAttribute("aria-pressed", "false");
      delete el.panel.dataset.playing;
    },
  });

  const setPath = (path) => state.setPath(path);
  const thumbnails = new Map(); // viewKey -> data URL of the view when it was recorded

  const showProblem = (message) => {
    if (message) alerts.set("movie-path", message, "warning");
    else alerts.clear("movie-path");
  };

  el.add.addEventListener("click", () => {
    if (!state.scene) return;
    player.stop();
    const path = state.path;
    const kf = {
      time: roundTo(nextKeyframeTime(path), 3),
      camera: state.keyframeCamera(),
      params: { ...state.params },
    };
    const pathOrtho = path.keyframes.length ? "view_height" in path.keyframes[0].camera : null;
    if (pathOrtho !== null && pathOrtho !== "view_height" in kf.camera) {
      const [was, now] = pathOrtho ? ["orthographic", "perspective"] : ["perspective", "orthographic"];
      showProblem(`This path is ${was} and the view is ${now}: a path keeps one projection. ` +
        `Switch the projection back to add to it, or remove its keyframes.`);
      return;
    }
    const thumbnail = thumbnailOf(el.canvas);
    if (thumbnail) thumbnails.set(viewKey(kf), thumbnail);
    setPath({ ...path, keyframes: [...path.keyframes, kf] });
    showProblem(null);
  });

  el.preview.addEventListener("click", () => {
    if (player.playing) {
      player.stop();
      return;
    }
    if (!state.path.keyframes.length) return;
    player.start(state.path);
    el.preview.textContent = "Stop";
    el.preview.setAttribute("aria-pressed", "true");
    el.panel.dataset.playing = "true";
  });
  // Taking hold of the view ends the preview.
  el.surface.addEventListener("pointerdown", () => player.stop());

  el.cameraMode.addEventListener("change", () => setPath({ ...state.path, camera_interpolation: el.cameraMode.value }));
  el.paramMode.addEventListener("change", () => setPath({ ...state.path, param_interpolation: el.paramMode.value }));

  el.save.addEventListener("click", () => {
    if (!state.path.keyframes.length) return;
    const text = JSON.stringify(normalizePath(state.path), null, 2) + "\n";
    const url = URL.createObjectURL(new Blob([text], { type: "application/json" }));
    const a = document.createElement("a");
    a.href = url;
    a.download = `${state.sceneId}_path.json`;
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
  });

  el.load.addEventListener("click", () => el.file.click());
  el.file.addEventListener("change", async () => {
    const file = el.file.files[0];
    el.file.value = "";
    if (!file || !state.scene) return;
    try {
      let doc;
      try {
        doc = JSON.parse(await file.text());
      } catch {
        throw new PathError("the file is not JSON");
      }
      player.stop();
      setPath(normalizePath(doc, state.scene.params, state.sceneCamera));
      showProblem(null);
    } catch (err) {
      if (!(err instanceof PathError)) throw err;
      showProblem(`Could not load the path from ${file.name}: ${err.message}.`);
    }
  });

  // ---- the strip ------------------------------------------------------------------------------

  const card = (kf, i, n) => {
    const item = document.createElement("li");
    item.className = "kf";
    item.dataset.index = String(i);
    const label = `keyframe ${i + 1}`;

    const show = document.createElement("button");
    show.type = "button";
    show.className = "kf-show";
    show.title = `Show ${label} in the view`;
    show.setAttribute("aria-label", `Show ${label} in the view`);
    const img = document.createElement("img");
    img.className = "kf-thumb";
    img.alt = "";
    img.loading = "lazy";
    img.addEventListener("error", () => img.removeAttribute("src"), { once: true });
    img.src = thumbnails.get(viewKey(kf)) || thumbnailUrl(state, kf);
    show.append(img);
    show.addEventListener("click", () => {
      player.stop();
      state.applyKeyframeCamera(kf.camera, { interactive: false });
      for (const [name, value] of Object.entries(kf.params)) state.setParam(name, value, { interactive: false });
    });

    const head = document.createElement("div");
    head.className = "kf-head";
    const index = document.createElement("span");
    index.className = "kf-index";
    index.textContent = String(i + 1);
    const time = document.createElement("input");
    time.type = "number";
    time.className = "kf-time";
    time.min = "0";
    time.step = "0.1";
    time.value = String(kf.time);
    time.setAttribute("aria-label", `Time of ${label}, in seconds`);
    time.addEventListener("change", () => {
      try {
        setPath(retimeKeyframe(state.path, i, time.value.trim() === "" ? NaN : Number(time.value)));
        showProblem(null);
      } catch (err) {
        if (!(err instanceof PathError)) throw err;
        time.setAttribute("aria-invalid", "true");
        showProblem(`Keyframe ${i + 1}: ${err.message}.`);
      }
    });
    const unit = document.createElement("span");
    unit.className = "muted small";
    unit.textContent = "s";
    head.append(index, time, unit);

    const buttons = document.createElement("div");
    buttons.className = "kf-buttons";
    const button = (cls, text, title, disabled, action) => {
      const b = document.createElement("button");
      b.type = "button";
      b.className = cls;
      b.textContent = text;
      b.title = title;
      b.setAttribute("aria-label", title);
      b.disabled = disabled;
      b.addEventListener("click", () => {
        player.stop();
        action();
      });
      buttons.append(b);
    };
    button("kf-earlier", "◀", `Move ${label} earlier`, i === 0, () => setPath(moveKeyframe(state.path, i, -1)));
    button("kf-later", "▶", `Move ${label} later`, i === n - 1, () => setPath(moveKeyframe(state.path, i, +1)));
    button("kf-remove", "✕", `Remove ${label}`, false, () => setPath(removeKeyframe(state.path, i)));

    const c = kf.camera;
    item.title =
      `az ${roundTo(c.azimuth, 1)}°, el ${roundTo(c.elevation, 1)}°, ` +
      `dist ${roundTo(c.distance, 3)}, ` +
      ("view_height" in c ? `view height ${roundTo(c.view_height, 3)}` : `fov ${roundTo(c.fov, 1)}°`) +
      Object.entries(kf.params).map(([name, v]) => `, ${name} ${roundTo(v, 4)}`).join("");
    item.append(show, head, buttons);
    return item;
  };

  const refresh = () => {
    const path = state.path;
    const n = path.keyframes.length;
    el.strip.replaceChildren(...path.keyframes.map((kf, i) => card(kf, i, n)));
    el.empty.hidden = n > 0;
    el.preview.disabled = n === 0;
    el.save.disabled = n === 0;
    el.cameraMode.value = path.camera_interpolation;
    el.paramMode.value = path.param_interpolation;
    el.summary.textContent = n ? `(${n} keyframe${n === 1 ? "" : "s"}, ${roundTo(pathDuration(path), 2)} s)` : "";
    el.panel.dataset.keyframes = String(n);
  };

  state.addEventListener("change", (event) => {
    const { type } = event.detail;
    if (type === "path" || type === "scene" || type === "restore") {
      if (type !== "path") player.stop();
      if (type === "scene") thumbnails.clear();
      refresh();
    }
  });
  refresh();

  return { player, frameCount: (fps) => (state.path.keyframes.length ? frameCount(state.path, fps) : 0) };
}
