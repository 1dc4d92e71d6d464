// The side panels: scene picker, scene facts, resolution choices, and "save as PNG".

import * as api from "./api.js";
import { formatValue } from "./controls.js";
import { roundTo } from "./state.js";

/** Long sides offered for full-quality frames (the training size is added to these). */
const RESOLUTIONS = [128, 192, 256, 384, 512, 768, 1024];

export function fillScenePicker(select, list, selected) {
  select.replaceChildren();
  if (!list.some((s) => s.id === selected)) {
    const option = new Option(list.length ? "— choose a scene —" : "no scenes", "");
    option.disabled = true;
    option.selected = true;
    select.append(option);
  }
  for (const scene of list) {
    const n = scene.params ? scene.params.length : 0;
    const option = new Option(`${scene.title || scene.id} (${scene.kind}, ${n} param${n === 1 ? "" : "s"})`, scene.id);
    option.selected = scene.id === selected;
    select.append(option);
  }
}

/** Default long side of a full frame: the training size, kept within [256, 512]. */
export function defaultResolution(scene) {
  const [w, h] = scene.image_size;
  return Math.min(512, Math.max(256, Math.max(w, h)));
}

export function showSceneInfo(kindChip, list, scene) {
  kindChip.hidden = false;
  kindChip.textContent = scene.kind === "ir" ? "isosurface (IR)" : scene.kind === "dvr" ? "volume (DVR)" : scene.kind;
  list.replaceChildren();
  const add = (term, value) => {
    if (value === undefined || value === null || value === "") return;
    const row = document.createElement("div");
    const dt = document.createElement("dt");
    dt.textContent = term;
    const dd = document.createElement("dd");
    dd.textContent = typeof value === "number" ? String(roundTo(value, 3)) : String(value);
    row.append(dt, dd);
    list.append(row);
  };
  add("id", scene.id);
  add("kind", scene.kind);
  add("trained at", `${scene.image_size[0]}×${scene.image_size[1]} px`);
  const ranges = scene.params.map((a) => `${a.name} [${formatValue(a.min, a)}, ${formatValue(a.max, a)}]`);
  add("parameters", ranges.join(", ") || "none");
  if (scene.camera.projection === "orthographic") {
    add("camera", "orthographic");
    if (Number.isFinite(scene.camera.view_height)) add("view height", scene.camera.view_height);
  } else if (Number.isFinite(scene.camera.fov_deg)) add("field of view", `${roundTo(scene.camera.fov_deg, 2)}°`);
  for (const [key, value] of Object.entries(scene.training || {})) {
    if (value !== null && typeof value === "object") continue;
    add(key.replace(/_/g, " "), value);
  }
}

export function fillResolutions(select, state) {
  select.replaceChildren();
  const [w, h] = state.scene.image_size;
  const trained = Math.max(w, h);
  const options = [...new Set([...RESOLUTIONS, trained, state.resolution])].sort((a, b) => a - b);
  select.append(new Option("Fit the view", "screen", false, state.fitScreen));
  for (const px of options) {
    const size = state.frameSize(px / state.resolution);
    const label = `${size.width}×${size.height}${px === trained ? " (trained)" : ""}`;
    select.append(new Option(label, String(px), false, !state.fitScreen && px === state.resolution));
  }
}

/** Export size: the training aspect, about 1024 pixels on the long side. */
export function fillExportSize(widthInput, heightInput, scene) {
  const [w, h] = scene.image_size;
  const k = Math.max(1, Math.round(1024 / Math.max(w, h)));
  widthInput.value = String(w * k);
  heightInput.value = String(h * k);
}

/** Retry a request the server refused with 503, after the delay it asked for (3 tries at most). */
export async function retryWhenBusy(attempt, onWait, tries = 3) {
  for (let i = 1; ; i += 1) {
    try {
      return await attempt();
    } catch (err) {
      if (err.status !== 503 || i >= tries) throw err;
      const delay = Number.isFinite(err.retryAfterS) && err.retryAfterS !== null ? err.retryAfterS : 1;
      onWait(delay);
      await new Promise((resolve) => setTimeout(resolve, delay * 1000));
    }
  }
}

/**
 * "Save PNG": render the current view (parameters A) at the chosen size through GET render and
 * download it with an <a download>; errors go to the alert line in words.
 */
export function setupExport({ state, alerts, width, height, button }) {
  width.addEventListener("input", () => {
    if (!state.scene) return;
    const [w, h] = state.scene.image_size;
    height.value = String(Math.max(16, Math.round((Number(width.value) * h) / w)));
  });

  button.addEventListener("click", async () => {
    const w = Math.round(Number(width.value));
    const h = Math.round(Number(height.value));
    if (!state.scene || !(w >= 16) || !(h >= 16)) {
      alerts.set("export", "Choose a width and a height of at least 16 pixels.", "warning");
      return;
    }
    button.disabled = true;
    button.textContent = "Rendering…";
    const req = {
      camera: { ...state.camera },
      ...state.lens(),
      width: w,
      height: h,
      params: { ...state.params },
      quality: "full",
      format: "png",
    };
    const sceneId = state.sceneId;
    try {
      const blob = await retryWhenBusy(
        () => api.fetchImage(sceneId, req),
        (delay) => alerts.set("export", `Server busy: it asked to retry in ${roundTo(delay, 1)} s. Retrying…`, "warning"),
      );
      const url = URL.createObjectURL(blob);
      const a = document.createElement("a");
      a.href = url;
      a.download = `${sceneId}_az${roundTo(req.camera.azimuth, 1)}_el${roundTo(req.camera.elevation, 1)}_${w}x${h}.png`;
      document.body.append(a);
      a.click();
      a.remove();
      setTimeout(() => URL.revokeObjectURL(url), 10000);
      alerts.clear("export");
    } catch (err) {
      alerts.set("export", `Could not save the image: ${err.message}`);
    } finally {
      button.disabled = false;
      button.textContent = "Save PNG";
    }
  });
}
