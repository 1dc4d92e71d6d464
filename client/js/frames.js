// Frame delivery for one view ("channel"): requests numbered by seq over the WebSocket (HTTP when
// the socket is down), the newest-frame-wins rule, and the preview/full schedule:
//   * while the user drags or slides: low-resolution JPEG previews, at most MAX_IN_FLIGHT
//     unanswered at a time (the newest state is sent when one comes back; the server also drops
//     stale requests),
//   * IDLE_MS after the last input: one full-quality PNG frame at the chosen resolution,
//   * SCREEN_IDLE_MS after that one is drawn, if the input is still: a full-quality frame at the
//     size the view is shown (its box times devicePixelRatio, within the server's limits), when
//     that is larger.

import { ApiError, HttpRenderer, RenderStream } from "./api.js";

export const IDLE_MS = 150;
/** While a pointer is still held (dragging the view or a slider thumb), a pause must last this
 * long before a full frame is rendered: a CPU full frame blocks the previews behind it. */
export const HELD_IDLE_MS = 600;
/** After the first preview of a view, the full frame is asked for when the preview is answered, or
 * after this long at the latest. */
const FIRST_FULL_WAIT_MS = 1500;
/** After a full frame at the chosen resolution is drawn, the wait before one at the view's size. */
export const SCREEN_IDLE_MS = 50;
const MAX_IN_FLIGHT = 2;
const OPEN_WAIT_MS = 1000; // how long a request waits for the socket before going over HTTP

/**
 * The preview size, adapted so previews render in about `targetMs`; shared by the channels of a
 * comparison so their previews have the same size (the difference image needs that).
 */
export class PreviewSizer {
  constructor({ targetMs = 35, minScale = 0.2, maxScale = 0.5, minLongSide = 64 } = {}) {
    this.targetMs = targetMs;
    this.minScale = minScale;
    this.maxScale = maxScale;
    this.minLongSide = minLongSide;
    this.scale = 0.5;
  }

  size(state) {
    const full = state.frameSize(1);
    const fullLong = Math.max(full.width, full.height);
    // Whole multiples of 16 pixels: sizes stay put while the scale drifts a little, so A and B
    // previews match and the server's frame cache can help.
    const long = Math.min(fullLong, Math.max(this.minLongSide, Math.round((fullLong * this.scale) / 16) * 16));
    return state.frameSize(long / fullLong);
  }

  observe(renderMs, pixels, fullPixels) {
    if (!Number.isFinite(renderMs) || renderMs <= 0 || !pixels) return;
    // Render time grows about linearly with the pixel count: aim the next preview at targetMs.
    const wanted = Math.sqrt((this.targetMs / renderMs) * (pixels / fullPixels));
    const next = Math.min(this.maxScale, Math.max(this.minScale, wanted));
    this.scale = 0.7 * this.scale + 0.3 * next;
  }
}

function requestKey(req) {
  return JSON.stringify([req.camera, req.fovDeg, req.viewHeight, req.width, req.height, req.params, req.quality, req.format]);
}

/** One stream of frames into one FrameView. */
export class FrameChannel {
  /**
   * @param {{name: string, sceneId: string, view: import("./viewer.js").FrameView,
   *          stats: import("./viewer.js").FrameStats,
   *          onShown: (frame) => void, onError: (err: ApiError, req) => void,
   *          onConnection: (info) => void}} options
   */
  constructor({ name, sceneId, view, stats, onShown, onError, onConnection }) {
    this.name = name;
    this.sceneId = sceneId;
    this.view = view;
    this.stats = stats;
    this.onShown = onShown;
    this.onError = onError;
    this.onConnection = onConnection;
    this.nextSeq = 1;
    this.lastShownSeq = 0;
    this.lastAnsweredSeq = 0;
    this.pending = new Map(); // seq -> {req, inputTime, sentAt}
    this.queued = []; // requests waiting for the socket to open (the newest two)
    this.openTimer = null;
    this.openTimerExpired = false;
    this.needsResend = false;
    this.openCount = 0; // 1 after the first connection, more after reconnections
    this.http = new HttpRenderer(sceneId);
    this.closed = false;
    this.onAnswer = () => {};
    this.onDrawn = () => {};
    this.stream = new RenderStream(sceneId, {
      onOpen: () => {
        this.openCount += 1;
        clearTimeout(this.openTimer);
        const queued = this.queued;
        this.queued = [];
        for (const q of queued) this.dispatch(q.seq, q.req);
        this.onConnection({ channel: this.name, state: "open" });
      },
      onFrame: (frame) => this.receive(frame),
      onError: (err) => this.receiveError(err),
      onClose: (info) => {
        // Requests sent on the dead socket will never be answered: ask again once it reopens.
        if (this.lastShownSeq < this.nextSeq - 1) this.needsResend = true;
        this.markAnswered(this.nextSeq - 1);
        this.onConnection({ channel: this.name, state: info.gone ? "gone" : "closed", ...info });
      },
    });
  }

  /** Number of sent requests not answered yet (answered = a frame or error with seq >= it came). */
  get inFlight() {
    let n = 0;
    for (const seq of this.pending.keys()) if (seq > this.lastAnsweredSeq) n += 1;
    return n;
  }

  /** Send a request; returns its seq. */
  request(req, inputTime) {
    const seq = this.nextSeq;
    this.nextSeq += 1;
    this.pending.set(seq, { req, inputTime, sentAt: performance.now(), key: requestKey(req) });
    if (this.stream.isOpen) {
      this.dispatch(seq, req);
    } else if (this.stream.ws && this.stream.ws.readyState === WebSocket.CONNECTING && !this.openTimerExpired) {
      // The socket is about to open: wait for it briefly rather than start an HTTP request.
      this.queued.push({ seq, req });
      if (this.queued.length > 2) this.queued.shift(); // superseded before it was ever sent
      if (!this.openTimer) {
        this.openTimer = setTimeout(() => {
          this.openTimerExpired = true;
          const queued = this.queued;
          this.queued = [];
          // HTTP renders cancel each other: only the newest is worth asking for.
          if (queued.length) this.viaHttp(queued.at(-1).seq, queued.at(-1).req);
        }, OPEN_WAIT_MS);
      }
    } else {
      this.viaHttp(seq, req);
    }
    return seq;
  }

  dispatch(seq, req) {
    if (!this.stream.send(seq, req)) this.viaHttp(seq, req);
  }

  async viaHttp(seq, req) {
    try {
      const { blob, renderMs } = await this.http.render(req);
      await this.receive({ seq, blob, renderMs, width: req.width, height: req.height, format: req.format });
    } catch (err) {
      if (err instanceof ApiError && err.kind === "aborted") return;
      this.receiveError({
        seq,
        status: err.status || 0,
        detail: err.detail,
        message: err.message,
        retryAfterS: err.retryAfterS,
        error: err,
      });
    }
  }

  markAnswered(seq) {
    if (seq > this.lastAnsweredSeq) this.lastAnsweredSeq = seq;
    this.onAnswer();
  }

  async receive(frame) {
    if (this.closed) return;
    this.markAnswered(frame.seq);
    // Never replace a newer frame by an older one that arrived late.
    if (frame.seq <= this.lastShownSeq) return;
    let bitmap;
    try {
      bitmap = await this.view.decode(frame.blob);
    } catch {
      this.onError(new ApiError("The server sent an image the browser could not decode"), null);
      return;
    }
    if (this.closed || frame.seq <= this.lastShownSeq || (this.view.blocked && this.view.blocked())) {
      bitmap.close(); // a newer frame was decoded and drawn meanwhile, or the browser draws the view
      return;
    }
    const entry = this.pending.get(frame.seq);
    const req = entry ? entry.req : { quality: "full" };
    // Latency: the oldest input this frame answers (requests since the last shown frame).
    let inputTime = null;
    for (const [seq, p] of this.pending) {
      if (seq > this.lastShownSeq && seq <= frame.seq && p.inputTime != null) {
        inputTime = inputTime === null ? p.inputTime : Math.min(inputTime, p.inputTime);
      }
    }
    this.lastShownSeq = frame.seq;
    for (const seq of this.pending.keys()) if (seq <= frame.seq) this.pending.delete(seq);
    this.view.draw(bitmap, { seq: frame.seq, quality: req.quality, key: entry ? entry.key : null, req });
    const record = this.stats.record({
      channel: this.name,
      seq: frame.seq,
      quality: req.quality,
      format: frame.format,
      width: this.view.canvas.width,
      height: this.view.canvas.height,
      renderMs: frame.renderMs,
      dropped: frame.dropped || 0,
      latencyMs: inputTime === null ? null : performance.now() - inputTime,
      requestMs: entry ? performance.now() - entry.sentAt : null,
      stage: req.stage || req.quality,
    });
    this.onShown(record, req);
    this.onDrawn(req);
  }

  receiveError(err) {
    if (this.closed) return;
    if (Number.isFinite(err.seq)) this.markAnswered(err.seq);
    const entry = Number.isFinite(err.seq) ? this.pending.get(err.seq) : null;
    if (entry) this.pending.delete(err.seq);
    const error =
      err.error ||
      new ApiError(err.message || `Render failed (status ${err.status})`, {
        status: err.status || 0,
        detail: err.detail,
        retryAfterS: err.retryAfterS,
      });
    this.onError(error, entry ? entry.req : null);
  }

  /** The request of the newest frame on screen (null before the first). */
  get shownRequest() {
    return this.view.shown ? this.view.shown.req : null;
  }

  close() {
    this.closed = true;
    clearTimeout(this.openTimer);
    this.http.cancel();
    this.stream.close();
  }
}

/**
 * Decides what a channel renders and when: previews during interaction, one full frame when the
 * input stops, then one at the view's size. `makeRequest(stage)` builds the request of a stage
 * ("preview", "full", "screen") from the current state; for "screen" it gives null when the view
 * is not larger than the full frame.
 */
export class RenderScheduler {
  constructor(channel, makeRequest, { idleMs = IDLE_MS, heldIdleMs = HELD_IDLE_MS } = {}) {
    this.channel = channel;
    this.makeRequest = makeRequest;
    this.idleMs = idleMs;
    this.heldIdleMs = heldIdleMs;
    this.held = false;
    this.firstPreviewSeq = null;
    this.dirty = false;
    this.pendingInputTime = null;
    this.idleTimer = null;
    this.rafId = null;
    this.retryTimer = null;
    this.lastFullKey = null;
    this.lastPreviewKey = null;
    this.screenTimer = null;
    this.onIdle = () => {};
    channel.onAnswer = () => this.pump();
    channel.onDrawn = (req) => {
      if (req && req.quality === "full" && req.stage !== "screen") this.sharpenSoon();
    };
  }

  /** A frame at the view's size after SCREEN_IDLE_MS, unless input comes first. */
  sharpenSoon() {
    clearTimeout(this.screenTimer);
    this.screenTimer = setTimeout(() => this.sharpen(), SCREEN_IDLE_MS);
  }

  cancelSharpen() {
    clearTimeout(this.screenTimer);
    this.screenTimer = null;
  }

  /** Whether the view shows the frame of request `req`. */
  shows(req) {
    const shown = this.channel.view.shown;
    return Boolean(req && shown && shown.key === requestKey(req));
  }

  /** The view's box changed: a still view is sharpened again at its new size. */
  resized() {
    const shown = this.channel.view.shown;
    if (shown && shown.quality === "full" && this.idleTimer === null && !this.dirty) this.sharpenSoon();
  }

  sharpen() {
    this.cancelSharpen();
    if (this.channel.closed || this.dirty || this.idleTimer !== null) return;
    const req = this.makeRequest("screen");
    if (!req || this.shows(req)) return;
    this.channel.request(req, performance.now());
  }

  /** Whether a frame at the view's size is still to come for the current state. */
  get screenDue() {
    if (this.screenTimer !== null) return true;
    const req = this.makeRequest("screen");
    return Boolean(req) && !this.shows(req);
  }

  /** An interactive change (drag, slider move): preview now, full frame after the idle delay. */
  input(inputTime = performance.now()) {
    this.cancelSharpen();
    if (this.pendingInputTime === null) this.pendingInputTime = inputTime;
    this.dirty = true;
    if (this.rafId === null) {
      this.rafId = requestAnimationFrame(() => {
        this.rafId = null;
        this.pump();
      });
    }
    clearTimeout(this.idleTimer);
    this.idleTimer = setTimeout(() => this.settle(), this.held ? this.heldIdleMs : this.idleMs);
  }

  /** The pointer is held (true) or released (false); a release starts the normal idle wait. */
  setHeld(held) {
    if (this.held === held) return;
    this.held = held;
    if (!held && this.idleTimer !== null) {
      clearTimeout(this.idleTimer);
      this.idleTimer = setTimeout(() => this.settle(), this.idleMs);
    }
  }

  /**
   * A first look (scene opened): a quick preview now, so something is on screen at once, and the
   * full frame straight after it.
   */
  start(inputTime = performance.now()) {
    const req = this.makeRequest("preview");
    this.lastPreviewKey = requestKey(req);
    // The full request waits for the preview's answer: sent together, the server would drop the
    // preview as stale and the first picture would take as long as a full frame.
    this.firstPreviewSeq = this.channel.request(req, inputTime);
    this.pendingInputTime = inputTime;
    this.idleTimer = setTimeout(() => this.settle(), FIRST_FULL_WAIT_MS);
  }

  /** A discrete change (button, typed value, restored URL): go straight to a full frame. */
  commit(inputTime = performance.now()) {
    this.cancelSharpen();
    if (this.pendingInputTime === null) this.pendingInputTime = inputTime;
    this.dirty = false;
    clearTimeout(this.idleTimer);
    this.idleTimer = setTimeout(() => this.settle(), 0);
  }

  pump() {
    if (this.firstPreviewSeq !== null && this.channel.lastAnsweredSeq >= this.firstPreviewSeq) {
      this.firstPreviewSeq = null;
      if (this.idleTimer !== null && !this.dirty) {
        clearTimeout(this.idleTimer);
        this.idleTimer = setTimeout(() => this.settle(), 0);
      }
    }
    if (!this.dirty || this.channel.closed) return;
    if (this.channel.inFlight >= MAX_IN_FLIGHT) return; // called again when an answer arrives
    const req = this.makeRequest("preview");
    const key = requestKey(req);
    this.dirty = false;
    if (key === this.lastPreviewKey) return;
    this.lastPreviewKey = key;
    this.channel.request(req, this.pendingInputTime);
    this.pendingInputTime = null;
  }

  /** True when nothing is scheduled and the newest request's full frame, at the view's size
   * where that is larger, is on screen. */
  get settled() {
    const c = this.channel;
    return (
      !this.dirty &&
      this.idleTimer === null &&
      c.lastShownSeq === c.nextSeq - 1 &&
      c.view.shown !== null &&
      c.view.shown.quality === "full" &&
      !this.screenDue
    );
  }

  settle({ force = false } = {}) {
    clearTimeout(this.idleTimer);
    this.idleTimer = null;
    this.dirty = false;
    if (this.channel.closed) return;
    const req = this.makeRequest("full");
    const key = requestKey(req);
    const shown = this.channel.view.shown;
    const screen = this.makeRequest("screen");
    const sharp = this.shows(screen);
    if (!force && shown && (sharp || (key === this.lastFullKey && shown.key === key))) {
      this.pendingInputTime = null;
      if (!sharp && screen) this.sharpenSoon(); // the full frame is shown; the view's size is not
      return;
    }
    this.lastFullKey = key;
    this.lastPreviewKey = null;
    this.channel.request(req, this.pendingInputTime ?? performance.now());
    this.pendingInputTime = null;
    this.onIdle();
  }

  /** Ask again after `delayS` seconds (a 503 told us when). */
  retryAfter(delayS) {
    clearTimeout(this.retryTimer);
    this.retryTimer = setTimeout(() => this.settle({ force: true }), Math.max(0.05, delayS) * 1000);
  }

  stop() {
    clearTimeout(this.idleTimer);
    this.idleTimer = null;
    this.cancelSharpen();
    clearTimeout(this.retryTimer);
    if (this.rafId !== null) cancelAnimationFrame(this.rafId);
    this.rafId = null;
  }
}
