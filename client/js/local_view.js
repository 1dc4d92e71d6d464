// View A drawn in the browser: the bake of the current parameter setting (GET
// /api/scenes/{id}/bake), marched by bake_renderer.js at the view's size times devicePixelRatio.
// Camera moves draw every animation frame with no server request. A setting with no bake held
// (a slider moving) is drawn by the server, as before; once it has been still for SETTLE_MS the
// bake of the new setting is fetched once (503 while the server builds it: asked again after its
// Retry-After), and drawn. Without WebGL2, or with a bake past the GPU's limits, server frames
// stay and `reason` says why. State for tests and benchmarks: window.__visnerfLocal.

import { parseBake } from "./bake.js";
import { BakeRenderer } from "./bake_renderer.js";

/** A setting must be still this long before its bake is fetched. */
export const SETTLE_MS = 250;

export function settingKey(sceneId, params) {
  return JSON.stringify([sceneId, Object.keys(params).sort().map((k) => [k, params[k]])]);
}

export class LocalView {
  /**
   * @param {{view: import("./viewer.js").FrameView, onStatus: (text: string, level: string) => void,
   *          onReady: (key: string) => void, onDrawn: (frame) => void}} options
   */
  constructor({ view, onStatus, onReady, onDrawn }) {
    this.view = view;
    this.onStatus = onStatus;
    this.onReady = onReady;
    this.onDrawn = onDrawn;
    this.forceServer = false;
    this.renderer = null;
    this.reason = "";
    try {
      this.renderer = new BakeRenderer();
    } catch (err) {
      this.reason = `${err.message}: every frame is drawn by the server`;
    }
    this.heldKey = null;
    this.wantedKey = null;
    this.fetchTimer = null;
    this.fetching = null;
    this.rafId = null;
    this.frameArgs = null;
    this.drawnKey = null;
    this.info = { source: "server", width: 0, height: 0, drawMs: null, bakesFetched: 0, bakeBytes: 0,
      textureBytes: 0, reason: this.reason, fetchMs: null };
    window.__visnerfLocal = this.info;
  }

  get supported() {
    return this.renderer !== null;
  }

  /** Whether view A is drawn here for the setting `key`. */
  active(key) {
    return this.supported && !this.forceServer && this.heldKey !== null && this.heldKey === key;
  }

  /** The setting shown changed (or the scene opened): fetch its bake once it has been still. */
  want(scene, params, key, { now = false } = {}) {
    if (!this.supported || this.forceServer) return;
    this.wantedKey = key;
    if (this.heldKey === key) return;
    clearTimeout(this.fetchTimer);
    this.fetchTimer = setTimeout(() => this.fetch(scene, params, key), now ? 0 : SETTLE_MS);
  }

  async fetch(scene, params, key) {
    if (this.wantedKey !== key || this.heldKey === key) return;
    if (this.fetching === key) return;
    this.fetching = key;
    const query = new URLSearchParams({ ...Object.fromEntries(Object.entries(params).map(([k, v]) => [k, String(v)])), v: scene.version });
    const started = performance.now();
    try {
      for (;;) {
        const response = await fetch(`/api/scenes/${encodeURIComponent(scene.id)}/bake?${query}`);
        if (this.wantedKey !== key) return; // moved on meanwhile
        if (response.status === 503) {
          const wait = Number(response.headers.get("Retry-After")) || 1;
          await new Promise((resolve) => setTimeout(resolve, wait * 1000));
          if (this.wantedKey !== key) return;
          continue;
        }
        if (!response.ok) {
          let detail = "";
          try {
            detail = (await response.json()).detail;
          } catch {
            detail = response.statusText;
          }
          throw new Error(`the server refused the bake (HTTP ${response.status}): ${detail}`);
        }
        const buffer = await response.arrayBuffer();
        const bake = parseBake(buffer);
        this.renderer.load(bake);
        this.heldKey = key;
        Object.assign(this.info, {
          bakesFetched: this.info.bakesFetched + 1, bakeBytes: buffer.byteLength, textureBytes: this.renderer.bytes,
          fetchMs: performance.now() - started, reason: "",
        });
        this.onStatus("", "info");
        this.onReady(key);
        return;
      }
    } catch (err) {
      this.info.reason = `${err.message}; frames come from the server`;
      this.onStatus(this.info.reason, "warning");
    } finally {
      if (this.fetching === key) this.fetching = null;
    }
  }

  /** Draw at the next animation frame: {key, camera, lens, width, height, meta, inputTime}; of
   * several asked for before it, the newest is drawn, answering the oldest input. */
  requestDraw(args) {
    const oldest = this.frameArgs && this.rafId !== null ? this.frameArgs.inputTime : null;
    this.frameArgs = oldest == null ? args : { ...args, inputTime: Math.min(oldest, args.inputTime ?? oldest) };
    if (this.rafId !== null) return;
    this.rafId = requestAnimationFrame(() => {
      this.rafId = null;
      const a = this.frameArgs;
      if (a && this.active(a.key)) this.drawNow(a);
    });
  }

  drawNow({ key, camera, lens, width, height, meta, inputTime }) {
    const ms = this.renderer.draw(camera, lens, width, height);
    this.view.drawSource(this.renderer.canvas, { ...meta, quality: "local" });
    this.drawnKey = meta.stateKey;
    Object.assign(this.info, { source: "local", width, height, drawMs: ms });
    this.onDrawn({ width, height, drawMs: ms, key, inputTime });
  }

  /** Server frames from now on (``on``), or local ones again. */
  setForceServer(on) {
    this.forceServer = on;
    if (on) this.info.source = "server";
  }

  /** A server frame was put on screen. */
  noteServerFrame() {
    this.info.source = "server";
    this.drawnKey = null;
  }

  reset() {
    clearTimeout(this.fetchTimer);
    this.heldKey = null;
    this.wantedKey = null;
    this.drawnKey = null;
    this.frameArgs = null;
    if (this.renderer) this.renderer.release();
    this.info.source = "server";
  }
}
