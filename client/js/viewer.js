// Drawing: decoded frames onto a <canvas>, the preview/full badge, and the frame statistics.

/** One canvas showing the frames of one render channel. */
export class FrameView {
  /**
   * @param {HTMLCanvasElement} canvas
   * @param {{badge?: HTMLElement, label?: string}} options
   */
  constructor(canvas, { badge = null, label = "Rendered view" } = {}) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d", { alpha: false, willReadFrequently: true });
    this.badge = badge;
    this.label = label;
    /** What is on screen: {seq, quality, width, height, key} or null. */
    this.shown = null;
  }

  /** Decode a frame; resolves to an ImageBitmap (the caller decides whether it is still wanted). */
  decode(blob) {
    return createImageBitmap(blob);
  }

  /** Put a decoded frame on screen. The canvas takes the frame's own size; CSS scales it to fit. */
  draw(bitmap, meta) {
    this.drawSource(bitmap, meta);
    bitmap.close();
  }

  /** Put any image source on screen (a decoded frame, the local renderer's WebGL canvas). */
  drawSource(source, meta) {
    if (this.canvas.width !== source.width || this.canvas.height !== source.height) {
      this.canvas.width = source.width;
      this.canvas.height = source.height;
    }
    this.ctx.drawImage(source, 0, 0);
    this.shown = { ...meta, width: this.canvas.width, height: this.canvas.height };
    this.canvas.dataset.seq = String(meta.seq);
    this.canvas.dataset.quality = meta.quality;
    this.canvas.classList.remove("empty");
    if (this.badge) {
      const titles = {
        full: `Full quality from the server, lossless PNG, ${this.canvas.width}×${this.canvas.height}`,
        preview: `Low-resolution preview from the server (JPEG, ${this.canvas.width}×${this.canvas.height}) while ` +
          "you move; the full-quality frame follows when you stop",
        local: `Drawn in this browser from the setting's bake, ${this.canvas.width}×${this.canvas.height}`,
      };
      this.badge.textContent = meta.quality;
      this.badge.dataset.quality = meta.quality;
      this.badge.title = titles[meta.quality] || "";
    }
  }

  /** RGBA pixels of what is on screen, or null when nothing is. */
  pixels() {
    if (!this.shown) return null;
    return this.ctx.getImageData(0, 0, this.canvas.width, this.canvas.height);
  }

  setDescription(text) {
    this.canvas.setAttribute("aria-label", `${this.label}: ${text}`);
  }

  clear() {
    this.shown = null;
    this.canvas.classList.add("empty");
    this.ctx.fillStyle = "#111";
    this.ctx.fillRect(0, 0, this.canvas.width, this.canvas.height);
    if (this.badge) {
      this.badge.textContent = "";
      delete this.badge.dataset.quality;
    }
  }
}

/**
 * Per-frame statistics, exposed as `window.__visnerfStats` for benchmarks and tests:
 *   firstFrameMs        page start (performance time origin) -> first frame on screen
 *   firstFullFrameMs    page start -> first full-quality frame on screen
 *   frames[]            {channel, seq, quality, width, height, renderMs, latencyMs, settleMs, shownAt}
 *                       latencyMs: oldest input answered by this frame -> frame drawn
 *                       settleMs (full frames): last input -> full frame drawn
 *   fps                 frames drawn per second over the last 2 s
 */
export class FrameStats {
  constructor(target = window) {
    this.frames = [];
    this.firstFrameMs = null;
    this.firstFullFrameMs = null;
    this.lastInputTime = null;
    this.maxFrames = 5000;
    target.__visnerfStats = this;
  }

  noteInput(time) {
    this.lastInputTime = time;
  }

  record(entry) {
    const shownAt = performance.now();
    const frame = { ...entry, shownAt };
    if (entry.quality === "full" && this.lastInputTime !== null) frame.settleMs = shownAt - this.lastInputTime;
    this.frames.push(frame);
    if (this.frames.length > this.maxFrames) this.frames.splice(0, this.frames.length - this.maxFrames);
    if (this.firstFrameMs === null) {
      this.firstFrameMs = shownAt;
      performance.mark("visnerf:first-frame");
    }
    if (this.firstFullFrameMs === null && entry.quality === "full") {
      this.firstFullFrameMs = shownAt;
      performance.mark("visnerf:first-full-frame");
    }
    return frame;
  }

  /** Frames of view A drawn per second over the last second (null unless frames are streaming). */
  get fps() {
    const now = performance.now();
    const recent = this.frames.filter((f) => f.channel === "A" && now - f.shownAt <= 1000);
    if (recent.length < 3) return null;
    const spanS = (recent.at(-1).shownAt - recent[0].shownAt) / 1000;
    return spanS >= 0.2 ? (recent.length - 1) / spanS : null;
  }

  reset() {
    this.frames = [];
  }
}

/** The status bar: frame size, render time, fps and quality of what is on screen. */
export class StatusBar {
  constructor(root) {
    this.size = root.querySelector("#stat-size");
    this.render = root.querySelector("#stat-render");
    this.latency = root.querySelector("#stat-latency");
    this.fps = root.querySelector("#stat-fps");
    this.quality = root.querySelector("#stat-quality");
  }

  show(frame, fps) {
    this.size.textContent = `${frame.width}×${frame.height}`;
    const where = frame.quality === "local" ? "draw" : "render";
    this.render.textContent = Number.isFinite(frame.renderMs) ? `${Math.round(frame.renderMs)} ms ${where}` : `– ms ${where}`;
    this.latency.textContent = Number.isFinite(frame.latencyMs) ? `${Math.round(frame.latencyMs)} ms to screen` : "";
    this.fps.textContent = fps === null ? "" : `${fps.toFixed(1)} fps`;
    this.quality.textContent = frame.quality;
    this.quality.dataset.quality = frame.quality;
  }

  clear() {
    for (const el of [this.size, this.render, this.latency, this.fps, this.quality]) el.textContent = "";
  }
}

/** The alert line: keyed messages (connection, render, scene...), the most severe one shown. */
export class AlertBox {
  constructor(element) {
    this.element = element;
    this.messages = new Map();
    this.order = 0;
  }

  set(key, message, level = "error") {
    const previous = this.messages.get(key);
    if (previous && previous.message === message && previous.level === level) return;
    this.order += 1;
    this.messages.set(key, { message, level, order: this.order });
    this.render();
  }

  clear(key) {
    if (this.messages.delete(key)) this.render();
  }

  has(key) {
    return this.messages.has(key);
  }

  render() {
    const rank = { error: 3, warning: 2, info: 1 };
    let best = null;
    for (const [key, m] of this.messages) {
      if (!best || rank[m.level] > rank[best.level] || (rank[m.level] === rank[best.level] && m.order > best.order)) {
        best = { key, ...m };
      }
    }
    if (!best) {
      this.element.hidden = true;
      this.element.textContent = "";
      delete this.element.dataset.key;
      return;
    }
    this.element.hidden = false;
    this.element.dataset.level = best.level;
    this.element.dataset.key = best.key;
    this.element.textContent = best.message;
  }
}
