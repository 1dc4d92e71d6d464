// Wiring: scene picker, state, controls, render channels, comparison, movie, URL and alerts.

import * as api from "./api.js";
import { DiffView } from "./compare.js";
import { buildParamControls, formatValue } from "./controls.js";
import { FrameChannel, PreviewSizer, RenderScheduler } from "./frames.js";
import { attachCameraInput } from "./interaction.js";
import { LocalView, settingKey } from "./local_view.js";
import { setupMoviePanel } from "./movie.js";
import { setupMovieJob } from "./movie_job.js";
import { defaultResolution, fillExportSize, fillResolutions, fillScenePicker, setupExport, showSceneInfo } from "./panels.js";
import { roundTo, ViewState } from "./state.js";
import { AlertBox, FrameStats, FrameView, StatusBar } from "./viewer.js";

const $ = (selector) => document.querySelector(selector);

const state = new ViewState();
const stats = new FrameStats();
const alerts = new AlertBox($("#alert"));
const statusBar = new StatusBar($("#statusbar"));
const views = {
  A: new FrameView($("#canvas-a"), { badge: $("#badge-a"), label: "View A" }),
  B: new FrameView($("#canvas-b"), { badge: $("#badge-b"), label: "View B" }),
};
const diff = new DiffView({
  canvas: $("#canvas-diff"),
  legend: $("#legend-bar"),
  ticks: $("#legend-ticks"),
  summary: $("#diff-summary"),
  scale: $("#diff-scale"),
  badge: $("#badge-diff"),
});
const sizer = new PreviewSizer();
let localSeq = 0;
const local = new LocalView({
  view: views.A,
  onStatus: (text, level) => {
    $("#local-status").textContent = text || localStatusText();
    if (text && level === "warning") alerts.set("local", text, "warning");
    else alerts.clear("local");
  },
  onReady: (key) => {
    if (key !== localKeyA()) return;
    schedulers.A?.stop(); // nothing the server draws for A is wanted now
    drawLocalA();
  },
  onDrawn: (frame) => {
    localSeq += 1;
    const record = stats.record({
      channel: "A", seq: localSeq, quality: "local", width: frame.width, height: frame.height, renderMs: frame.drawMs,
      latencyMs: frame.inputTime == null ? null : performance.now() - frame.inputTime, stage: "local",
    });
    statusBar.show(record, stats.fps);
    alerts.clear("render");
    alerts.clear("busy");
    if (state.compare) diff.schedule(views.A, views.B);
  },
});
views.A.blocked = () => localActiveA();

function localStatusText() {
  if (!local.supported) return local.reason;
  if (local.forceServer) return "Every frame is drawn by the server.";
  return localActiveA() ? "Camera moves are drawn in this browser from the setting's bake." : "";
}

function localKeyA() {
  return settingKey(state.sceneId, state.params);
}

function localActiveA() {
  return state.scene !== null && state.scene !== undefined && local.active(localKeyA());
}

/** What view A shows when drawn here: camera, lens, setting and size. */
function localStateKey(box) {
  return JSON.stringify([state.camera, state.lens(), state.params, box.width, box.height]);
}

/** The size view A is drawn at locally: its box in device pixels, 16 at least. */
function localSize() {
  const box = viewBox("A");
  return { width: Math.max(16, box.width), height: Math.max(16, box.height) };
}

function drawLocalA(inputTime = null) {
  const { width, height } = localSize();
  const req = { camera: { ...state.camera }, ...state.lens(), width, height, params: { ...state.params }, quality: "local" };
  local.requestDraw({
    key: localKeyA(), camera: { ...state.camera }, lens: state.lens(), width, height, inputTime,
    meta: { seq: localSeq + 1, key: null, req, stateKey: localStateKey({ width, height }) },
  });
  $("#local-status").textContent = localStatusText();
}
const channels = { A: null, B: null };
const schedulers = { A: null, B: null };
const controls = { A: null, B: null };
let sceneList = [];
let urlTimer = null;
let openGeneration = 0;
/** The server's frame limits (GET /api/limits); its defaults until they are known. */
let frameLimits = { max_side: 2048, max_full_pixels: 1920 * 1080 };
api.getLimits().then((limits) => (frameLimits = limits), () => {});

// ---- scenes -----------------------------------------------------------------------------------

async function boot() {
  const query = new URLSearchParams(location.search);
  showServerInfo();
  try {
    sceneList = await api.listScenes();
  } catch (err) {
    // 503: the server is still loading its scenes (it says when to ask again).
    const starting = err.status === 503;
    const waitS = starting && err.retryAfterS ? err.retryAfterS : 3;
    alerts.set("scenes", starting ? "Server starting: loading its scenes…" : `${err.message}. Retrying in 3 s…`,
      starting ? "warning" : undefined);
    setTimeout(boot, waitS * 1000);
    return;
  }
  alerts.clear("scenes");
  fillScenePicker($("#scene-select"), sceneList, state.sceneId);
  if (!sceneList.length) {
    alerts.set("scenes", "The server has no scenes loaded. Add a checkpoint and reload the page.", "warning");
    return;
  }
  const wanted = query.get("scene");
  const chosen = sceneList.some((s) => s.id === wanted) ? wanted : sceneList[0].id;
  if (wanted && wanted !== chosen) {
    alerts.set("link", `Scene '${wanted}' is not on this server; showing '${chosen}' instead.`, "warning");
  }
  await openScene(chosen, wanted === chosen ? query : null);
}

async function showServerInfo() {
  try {
    const health = await api.getHealth();
    $("#server-info").textContent = `server ${health.version ?? ""} · ${health.scenes ?? "?"} scene(s)`;
  } catch {
    $("#server-info").textContent = "";
  }
}

async function openScene(sceneId, query = null) {
  const generation = ++openGeneration;
  closeChannels();
  let scene;
  try {
    scene = await api.getScene(sceneId);
  } catch (err) {
    if (generation !== openGeneration) return;
    if (err.status === 404) {
      alerts.set("scene", `Scene '${sceneId}' is no longer available on the server.`);
      refreshSceneList();
    } else {
      alerts.set("scene", `${err.message}. Retrying in 3 s…`);
      setTimeout(() => generation === openGeneration && openScene(sceneId, query), 3000);
    }
    return;
  }
  if (generation !== openGeneration) return;
  alerts.clear("scene");
  state.setScene(scene);
  scene = state.scene;
  state.resolution = defaultResolution(scene);
  state.fitScreen = true;
  if (query) state.applyQuery(query);
  if (state.pathWarning) {
    alerts.set("link-path", `The camera path in this link is malformed (${state.pathWarning}); it was left out.`, "warning");
  }
  fillScenePicker($("#scene-select"), sceneList, scene.id);
  showSceneInfo($("#scene-kind"), $("#scene-info"), scene);
  fillResolutions($("#resolution"), state);
  fillExportSize($("#export-width"), $("#export-height"), scene);
  controls.A = buildParamControls($("#params-a"), scene.params, {
    set: "A",
    onInput: (name, value, o) => state.setParam(name, value, { set: "A", ...o }),
  });
  controls.B = buildParamControls($("#params-b"), scene.params, {
    set: "B",
    onInput: (name, value, o) => state.setParam(name, value, { set: "B", ...o }),
  });
  controls.A.update(state.params);
  controls.B.update(state.paramsB);
  views.A.clear();
  views.B.clear();
  diff.clear();
  statusBar.clear();
  showCamera();
  applyCompareLayout();
  local.reset();
  openChannel("A");
  if (state.compare) openChannel("B");
  local.want(scene, state.params, localKeyA(), { now: true });
  writeUrlSoon();
}

async function refreshSceneList() {
  try {
    sceneList = await api.listScenes();
    fillScenePicker($("#scene-select"), sceneList, state.sceneId);
  } catch (err) {
    alerts.set("connection", err.message);
  }
}

// ---- render channels --------------------------------------------------------------------------

/** The box a view's frames are shown in, in device pixels (the canvas scales its frame to fit). */
function viewBox(set) {
  const canvas = views[set].canvas;
  const dpr = window.devicePixelRatio || 1;
  return { width: Math.floor(canvas.clientWidth * dpr), height: Math.floor(canvas.clientHeight * dpr) };
}

/** Request of a stage: "preview", "full" (the chosen resolution) or "screen" (the view's size, or
 * null when that is not larger). */
function requestBuilder(set) {
  return (stage) => {
    let size = stage === "preview" ? sizer.size(state) : state.fullSize();
    if (stage === "screen") {
      size = state.screenSize(viewBox(set), frameLimits);
      if (!size) return null;
    }
    const quality = stage === "preview" ? "preview" : "full";
    return {
      camera: { ...state.camera },
      ...state.lens(),
      width: size.width,
      height: size.height,
      params: { ...(set === "B" ? state.paramsB : state.params) },
      quality,
      format: quality === "full" ? "png" : "jpeg",
      ...(stage === "screen" ? { stage } : {}),
    };
  };
}

function openChannel(set) {
  if (channels[set]) return;
  const sceneId = state.sceneId;
  const channel = new FrameChannel({
    name: set,
    sceneId,
    view: views[set],
    stats,
    onShown: (frame, req) => onFrameShown(set, frame, req),
    onError: (err, req) => onRenderError(set, err, req),
    onConnection: (info) => onConnection(set, info),
  });
  const scheduler = new RenderScheduler(channel, requestBuilder(set));
  channels[set] = channel;
  schedulers[set] = scheduler;
  scheduler.start();
}

function closeChannel(set) {
  if (!channels[set]) return;
  schedulers[set].stop();
  channels[set].close();
  channels[set] = null;
  schedulers[set] = null;
}

function closeChannels() {
  closeChannel("A");
  closeChannel("B");
}

function setOffline(on) {
  if (on) document.body.dataset.offline = "true";
  else delete document.body.dataset.offline;
}

function onFrameShown(set, frame, req) {
  setOffline(false);
  if (set === "A") local.noteServerFrame();
  alerts.clear("render");
  alerts.clear("busy");
  if (!channels[set] || !channels[set].stream.isOpen) {
    // Frames still arrive over HTTP: the server is up even though the stream is down.
    if (alerts.has("connection")) alerts.set("connection", "Render stream lost; reconnecting (frames come over HTTP meanwhile).", "warning");
  }
  if (req.quality === "preview") {
    const full = state.frameSize();
    sizer.observe(frame.renderMs, frame.width * frame.height, full.width * full.height);
  }
  if (set === "A") {
    statusBar.show(frame, stats.fps);
    views.A.setDescription(describeView(req));
  }
  if (state.compare) diff.schedule(views.A, views.B);
}

function describeView(req) {
  const params = Object.entries(req.params)
    .map(([name, v]) => `${name} ${formatValue(v, state.axis(name) || { min: 0, max: 1 })}`)
    .join(", ");
  return (
    `${state.scene.title || state.scene.id} at azimuth ${req.camera.azimuth.toFixed(1)}°, ` +
    `elevation ${req.camera.elevation.toFixed(1)}°${params ? `, ${params}` : ""} (${req.quality})`
  );
}

function onRenderError(set, err, req) {
  const scheduler = schedulers[set];
  if (err.status === 503 || err.status === 429) {
    // 503: the render queue is full; 429: this browser asked for more pixels a second than the
    // server grants one client. Both say when to ask again (Retry-After).
    const delay = Number.isFinite(err.retryAfterS) && err.retryAfterS !== null ? err.retryAfterS : 1;
    const why = err.status === 503 ? "Server busy" : "Rate limited (too many pixels a second from this page)";
    alerts.set("busy", `${why}: it asked to retry in ${roundTo(delay, 1)} s. Retrying automatically…`, "warning");
    if (scheduler) scheduler.retryAfter(delay);
    return;
  }
  if (err.status === 404) {
    checkSceneStillThere();
    return;
  }
  if (err.status === 0 || err.kind === "unreachable") {
    alerts.set("connection", "Server unreachable: the render server does not answer. Retrying…");
    setOffline(true);
    return;
  }
  const what = req ? `${req.quality} frame ${req.width}×${req.height}` : "frame";
  const text = err.message && err.message.startsWith("Render") ? err.message : `Render refused (HTTP ${err.status}): ${err.message}`;
  alerts.set("render", `${text} [${what}]`);
}

let checkingScene = false;

/**
 * The server said the scene is unknown. A server that has just (re)started answers that for every
 * scene until it has loaded them (GET /api/ready is 503 meanwhile): wait for it, then ask again;
 * only a ready server that does not list the scene means it is gone.
 */
async function checkSceneStillThere() {
  if (checkingScene) return;
  checkingScene = true;
  const id = state.sceneId;
  try {
    for (let attempt = 0; attempt < 120; attempt += 1) {
      try {
        await api.getReady();
        break;
      } catch (err) {
        if (err.status === 404) break; // no readiness endpoint: take the answer as it is
        const wait = err.status === 503 && err.retryAfterS ? err.retryAfterS : 1;
        alerts.set("connection", err.status === 503 ? "Server starting: loading its scenes…" : err.message, "warning");
        await new Promise((resolve) => setTimeout(resolve, wait * 1000));
      }
      if (state.sceneId !== id) return;
    }
    try {
      await api.getScene(id);
    } catch (err) {
      if (err.status === 404 && state.sceneId === id) sceneGone();
      return;
    }
    // Still there: reconnect and carry on.
    alerts.clear("connection");
    for (const set of activeSets()) {
      channels[set]?.stream.reconnectNow();
      schedulers[set]?.settle({ force: true });
    }
  } finally {
    checkingScene = false;
  }
}

function sceneGone() {
  const id = state.sceneId;
  closeChannels();
  alerts.set("scene", `Scene '${id}' is no longer available on the server (404). Choose another scene.`);
  refreshSceneList();
}

async function onConnection(set, info) {
  if (info.state === "open") {
    if (set === "A") {
      alerts.clear("connection");
      setOffline(false);
    }
    const channel = channels[set];
    if (channel && channel.needsResend) {
      channel.needsResend = false;
      schedulers[set].settle({ force: true });
    } else if (channel && channel.openCount > 1) {
      schedulers[set].settle(); // reconnected: catch up with changes made while the server was away
    }
    return;
  }
  if (set !== "A") return;
  if (info.state === "gone") {
    checkSceneStillThere();
    return;
  }
  const wait = info.retryInS ? ` in ${Math.max(1, Math.round(info.retryInS))} s` : "";
  try {
    await api.getHealth();
    if (channels.A && !channels.A.stream.isOpen) {
      alerts.set("connection", `Render stream closed; reconnecting${wait}…`, "warning");
    }
  } catch {
    if (channels.A && !channels.A.stream.isOpen) {
      alerts.set("connection", `Server unreachable: cannot connect to ${location.host}. Reconnecting${wait}…`);
      setOffline(true);
    }
  }
}

// ---- state changes ----------------------------------------------------------------------------

function activeSets() {
  return state.compare ? ["A", "B"] : ["A"];
}

function kick(sets, interactive, inputTime) {
  const t = Number.isFinite(inputTime) ? inputTime : performance.now();
  stats.noteInput(t);
  for (const set of sets) {
    if (set === "A" && localActiveA()) {
      drawLocalA(t); // drawn here at the next animation frame: no server request
      continue;
    }
    const scheduler = schedulers[set];
    if (!scheduler) continue;
    if (interactive) scheduler.input(t);
    else scheduler.commit(t);
  }
}

function showCamera() {
  $("#az-value").textContent = state.camera.azimuth.toFixed(1);
  $("#el-value").textContent = state.camera.elevation.toFixed(1);
  $("#dist-value").textContent = state.camera.distance.toFixed(3);
  const ortho = state.projection === "orthographic";
  $("#lens-label").textContent = ortho ? "View height" : "Field of view";
  $("#lens-value").textContent = ortho ? state.viewHeight.toFixed(3) : `${state.fovDeg.toFixed(1)}°`;
  $("#projection").value = state.projection;
  $("#viewport").setAttribute(
    "aria-label",
    `View. Azimuth ${state.camera.azimuth.toFixed(0)} degrees, elevation ${state.camera.elevation.toFixed(0)} degrees. ` +
      "Use arrow keys to orbit, plus and minus to zoom.",
  );
}

function applyCompareLayout() {
  $("#compare-toggle").checked = state.compare;
  $("#panes").classList.toggle("compare", state.compare);
  $("#pane-b").hidden = !state.compare;
  $("#pane-diff").hidden = !state.compare;
  $("#pane-legend").hidden = !state.compare;
  $("#compare-body").hidden = !state.compare;
  $("#pane-a-caption").textContent = state.compare ? "current parameters" : "";
  const [w, h] = (state.scene && state.scene.image_size) || [1, 1];
  $("#panes").style.setProperty("--frame-aspect", String(w / h));
}

function writeUrlSoon() {
  clearTimeout(urlTimer);
  urlTimer = setTimeout(() => state.writeUrl(), 200);
}

state.addEventListener("change", (event) => {
  const { type, interactive, inputTime } = event.detail;
  if (!state.scene) return;
  switch (type) {
    case "camera":
      showCamera();
      kick(activeSets(), interactive, inputTime);
      break;
    case "params":
      controls.A?.update(state.params);
      kick(["A"], interactive, inputTime);
      local.want(state.scene, state.params, localKeyA());
      break;
    case "paramsB":
      controls.B?.update(state.paramsB);
      kick(["B"], interactive, inputTime);
      break;
    case "compare":
      applyCompareLayout();
      if (state.compare) {
        openChannel("B");
      } else {
        closeChannel("B");
        views.B.clear();
        diff.clear();
      }
      break;
    case "resolution":
      kick(activeSets(), false);
      break;
    case "path":
      break;
    default:
      return;
  }
  writeUrlSoon();
});

// ---- page controls ----------------------------------------------------------------------------

$("#scene-select").addEventListener("change", (event) => {
  const id = event.target.value;
  alerts.clear("link");
  alerts.clear("link-path");
  if (id && id !== state.sceneId) openScene(id);
});

$("#reset-view").addEventListener("click", () => state.resetCamera());
$("#projection").addEventListener("change", (event) => state.setProjection(event.target.value));

$("#resolution").addEventListener("change", (event) => state.chooseResolution(event.target.value));
new ResizeObserver(() => {
  if (localActiveA()) drawLocalA();
  for (const set of activeSets()) if (set !== "A" || !localActiveA()) schedulers[set]?.resized();
}).observe($("#canvas-a"));

/** The user's choice of server frames only, kept across visits. */
const SERVER_FRAMES_KEY = "visnerf.serverFrames";
try {
  $("#server-frames").checked = localStorage.getItem(SERVER_FRAMES_KEY) === "1";
} catch {
  // storage refused (private mode): the default, local frames where possible
}
local.setForceServer($("#server-frames").checked);
$("#local-status").textContent = localStatusText();

$("#server-frames").addEventListener("change", (event) => {
  local.setForceServer(event.target.checked);
  try {
    localStorage.setItem(SERVER_FRAMES_KEY, event.target.checked ? "1" : "0");
  } catch {
    // not kept; the choice still holds on this page
  }
  $("#local-status").textContent = localStatusText();
  if (event.target.checked) schedulers.A?.settle({ force: true });
  else if (localActiveA()) drawLocalA();
  else local.want(state.scene, state.params, localKeyA(), { now: true });
});

$("#compare-toggle").addEventListener("change", (event) => state.setCompare(event.target.checked));

$("#pin-b").addEventListener("click", () => {
  state.pinAsB();
  state.setCompare(true);
});

$("#swap-ab").addEventListener("click", () => {
  const a = state.params;
  state.params = state.paramsB;
  state.paramsB = a;
  state.emit("params", { interactive: false });
  state.emit("paramsB", { interactive: false });
});

setupExport({
  state,
  alerts,
  width: $("#export-width"),
  height: $("#export-height"),
  button: $("#save-png"),
});

const movie = setupMoviePanel({
  state,
  alerts,
  el: {
    panel: $("#movie-panel"),
    canvas: $("#canvas-a"),
    surface: $("#panes"),
    add: $("#kf-add"),
    preview: $("#movie-preview"),
    strip: $("#kf-strip"),
    empty: $("#kf-empty"),
    summary: $("#movie-summary"),
    cameraMode: $("#path-camera"),
    paramMode: $("#path-params"),
    save: $("#path-save"),
    load: $("#path-load"),
    file: $("#path-file"),
  },
});

setupMovieJob({
  state,
  alerts,
  panel: movie,
  el: {
    fps: $("#movie-fps"),
    width: $("#movie-width"),
    height: $("#movie-height"),
    format: $("#movie-format"),
    quality: $("#movie-quality"),
    render: $("#movie-render"),
    estimate: $("#movie-estimate"),
    job: $("#movie-job"),
    progress: $("#movie-progress"),
    status: $("#movie-status"),
    cancel: $("#movie-cancel"),
    download: $("#movie-download"),
  },
});

attachCameraInput($("#panes"), state, { onInput: (t) => stats.noteInput(t) });

// A held pointer (dragging the view or a slider thumb) postpones full frames until release.
const setHeld = (held) => {
  for (const set of ["A", "B"]) schedulers[set]?.setHeld(held);
};
document.addEventListener("pointerdown", () => setHeld(true), true);
for (const type of ["pointerup", "pointercancel"]) document.addEventListener(type, () => setHeld(false), true);
window.addEventListener("blur", () => setHeld(false));

window.__visnerfState = state;
/** For tests and benchmarks: every active view shows the full frame of its newest request. */
window.__visnerfSettled = () =>
  activeSets().every((set) => {
    if (set === "A" && localActiveA()) return local.drawnKey === localStateKey(localSize());
    return schedulers[set] !== null && schedulers[set].settled;
  });
boot();
