// "Render movie": sends the path to the server as a movie job, shows its progress (frames done of
// the total, frames per second, time left) by polling its status, offers Cancel while it runs and
// a Download link when it is done; a refusal or a failure is shown with the server's reason.

import * as api from "./api.js";
import { normalizePath } from "./path.js";
import { roundTo } from "./state.js";

const POLL_MS = 400;
const FINAL = new Set(["done", "failed", "cancelled"]);
const RUNNING = new Set(["starting", "queued", "running"]);

function formatSeconds(seconds) {
  const s = Math.ceil(seconds);
  if (s < 60) return `${s} s`;
  return `${Math.floor(s / 60)} min ${String(s % 60).padStart(2, "0")} s`;
}

/**
 * Wire the render controls. `el`: fps, width, height, format, quality, render, estimate, job,
 * progress, status, cancel, download. `panel` is what setupMoviePanel returned.
 */
export function setupMovieJob({ state, alerts, el, panel }) {
  let job = null; // {statusUrl, fileUrl, format, sceneId}
  let pollTimer = null;
  let controller = null;

  const setJobState = (name) => {
    el.job.hidden = false;
    el.job.dataset.state = name;
    el.cancel.hidden = !RUNNING.has(name) || name === "starting";
    el.render.disabled = RUNNING.has(name);
  };

  const showEstimate = () => {
    const fps = Number(el.fps.value);
    const n = Number.isFinite(fps) && fps > 0 ? panel.frameCount(fps) : 0;
    el.estimate.textContent = n ? `${n} frame${n === 1 ? "" : "s"}` : "";
    el.render.disabled = !state.path.keyframes.length || RUNNING.has(el.job.dataset.state);
  };

  const fillSize = () => {
    if (!state.scene) return;
    const [w, h] = state.scene.image_size;
    const k = 512 / Math.max(w, h);
    el.width.value = String(2 * Math.round((w * k) / 2));
    el.height.value = String(2 * Math.round((h * k) / 2));
  };
  el.width.addEventListener("input", () => {
    if (!state.scene) return;
    const [w, h] = state.scene.image_size;
    el.height.value = String(Math.max(16, 2 * Math.round((Number(el.width.value) * h) / w / 2)));
  });

  const showStatus = (s) => {
    const total = s.frames_total || 0;
    const done = s.frames_done || 0;
    el.progress.max = Math.max(1, total);
    el.progress.value = done;
    const parts = [`${done} / ${total} frames`];
    const fps = s.frames_per_second;
    if (Number.isFinite(fps) && fps > 0) parts.push(`${roundTo(fps, 1)} fps`);
    if (s.state === "running" && Number.isFinite(s.seconds_left)) parts.push(`${formatSeconds(s.seconds_left)} left`);
    const words = { queued: "Queued", running: "Rendering", done: "Done", cancelled: "Cancelled", failed: "Failed" };
    el.status.textContent = `${words[s.state] || s.state}: ${parts.join(" · ")}`;
    el.status.dataset.level = s.state === "failed" ? "error" : "";
    setJobState(s.state);
    if (s.state === "done") {
      el.download.href = job.fileUrl;
      el.download.download = `${job.sceneId}_movie.${job.format}`;
      el.download.hidden = false;
      alerts.clear("movie");
    }
    if (s.state === "failed") {
      const why = api.describeDetail(s.error) || "no reason given";
      el.status.textContent = `Failed: ${why}`;
      alerts.set("movie", `The movie could not be rendered: ${why}`);
    }
  };

  const poll = async () => {
    pollTimer = null;
    if (!job) return;
    const current = job;
    controller = new AbortController();
    let s;
    try {
      s = await api.getMovieStatus(current.statusUrl, { signal: controller.signal });
    } catch (err) {
      if (err.kind === "aborted" || job !== current) return;
      if (err.status === 404) {
        el.status.textContent = "The server no longer knows this movie (it may have restarted).";
        setJobState("failed");
        job = null;
        return;
      }
      el.status.textContent = `${err.message}; trying again…`;
      pollTimer = setTimeout(poll, 4 * POLL_MS);
      return;
    }
    if (job !== current) return;
    showStatus(s);
    if (!FINAL.has(s.state)) pollTimer = setTimeout(poll, POLL_MS);
  };

  const stopPolling = () => {
    clearTimeout(pollTimer);
    pollTimer = null;
    if (controller) controller.abort();
  };

  el.render.addEventListener("click", async () => {
    if (!state.scene || !state.path.keyframes.length) return;
    const body = {
      path: normalizePath(state.path),
      fps: Number(el.fps.value),
      width: Math.round(Number(el.width.value)),
      height: Math.round(Number(el.height.value)),
      format: el.format.value,
      quality: el.quality.value,
    };
    panel.player.stop();
    stopPolling();
    job = null;
    el.download.hidden = true;
    el.download.removeAttribute("href");
    el.progress.value = 0;
    el.status.textContent = "Sending the path…";
    el.status.dataset.level = "";
    setJobState("starting");
    const sceneId = state.sceneId;
    try {
      const created = await api.createMovie(sceneId, body);
      const statusUrl = created.status_url || api.movieStatusUrl(created.job_id);
      job = { statusUrl, fileUrl: created.file_url || `${statusUrl}/file`, format: body.format, sceneId };
      showStatus({ state: "queued", frames_done: 0, frames_total: created.frames });
      poll();
    } catch (err) {
      el.status.textContent = `Not started: ${err.message}`;
      el.status.dataset.level = "error";
      setJobState("failed");
      alerts.set("movie", `Could not start the movie: ${err.message}`);
    }
  });

  el.cancel.addEventListener("click", async () => {
    if (!job) return;
    el.cancel.disabled = true;
    try {
      await api.cancelMovie(job.statusUrl);
    } catch (err) {
      alerts.set("movie", `Could not cancel the movie: ${err.message}`);
    } finally {
      el.cancel.disabled = false;
    }
    stopPolling();
    poll();
  });

  el.fps.addEventListener("input", showEstimate);
  state.addEventListener("change", (event) => {
    const { type } = event.detail;
    if (type === "scene") fillSize();
    if (type === "path" || type === "scene" || type === "restore") showEstimate();
  });
  showEstimate();
}
