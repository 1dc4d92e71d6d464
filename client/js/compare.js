// Comparison view: the CIELUV difference of the frames A and B (same camera, two parameter
// tuples), coloured through a fixed legend whose scale is labelled.

import { colourizeDelta, deltaEuv, legendColour } from "./luv.js";

export const LEGEND_SCALES = [5, 10, 20, 40, 80];

function sameView(a, b) {
  if (!a || !b || !a.req || !b.req) return false;
  const ca = a.req.camera;
  const cb = b.req.camera;
  return (
    a.width === b.width &&
    a.height === b.height &&
    a.req.fovDeg === b.req.fovDeg &&
    a.req.viewHeight === b.req.viewHeight &&
    ca.azimuth === cb.azimuth &&
    ca.elevation === cb.elevation &&
    ca.distance === cb.distance
  );
}

export class DiffView {
  /**
   * @param {{canvas: HTMLCanvasElement, legend: HTMLCanvasElement, ticks: HTMLElement,
   *          summary: HTMLElement, scale: HTMLSelectElement, badge: HTMLElement}} elements
   */
  constructor({ canvas, legend, ticks, summary, scale, badge }) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d", { alpha: false });
    this.legend = legend;
    this.ticks = ticks;
    this.summary = summary;
    this.scaleSelect = scale;
    this.badge = badge;
    this.scaleMax = Number(scale.value) || 20;
    this.last = null; // {delta, width, height} of the last computed difference
    this.pendingViews = null;
    this.rafId = null;
    scale.addEventListener("change", () => {
      this.scaleMax = Number(scale.value) || 20;
      this.drawLegend();
      if (this.last) this.paint(this.last);
    });
    this.drawLegend();
  }

  drawLegend() {
    const ctx = this.legend.getContext("2d");
    const w = this.legend.width;
    const h = this.legend.height;
    for (let x = 0; x < w; x += 1) {
      const [r, g, b] = legendColour(x / (w - 1));
      ctx.fillStyle = `rgb(${r},${g},${b})`;
      ctx.fillRect(x, 0, 1, h);
    }
    this.ticks.replaceChildren();
    const n = 4;
    for (let i = 0; i <= n; i += 1) {
      const v = (this.scaleMax * i) / n;
      const tick = document.createElement("span");
      tick.style.setProperty("--pos", String(i / n));
      tick.textContent = i === n ? `≥${v}` : String(Number(v.toFixed(2)));
      this.ticks.append(tick);
    }
    this.legend.setAttribute(
      "aria-label",
      `Colour legend: dark means no difference, bright yellow means a CIELUV difference of ${this.scaleMax} or more`,
    );
  }

  /** Recompute from the two views on the next animation frame (coalesces bursts of frames). */
  schedule(viewA, viewB) {
    this.pendingViews = [viewA, viewB];
    if (this.rafId !== null) return;
    this.rafId = requestAnimationFrame(() => {
      this.rafId = null;
      const [a, b] = this.pendingViews;
      this.update(a, b);
    });
  }

  update(viewA, viewB) {
    if (!sameView(viewA.shown, viewB.shown)) {
      this.summary.textContent = "Waiting for A and B at the same view…";
      return false;
    }
    const pa = viewA.pixels();
    const pb = viewB.pixels();
    const result = deltaEuv(pa.data, pb.data);
    const preview = viewA.shown.quality !== "full" || viewB.shown.quality !== "full";
    this.last = { ...result, width: pa.width, height: pa.height, preview };
    this.paint(this.last);
    const f = (x) => x.toFixed(x < 10 ? 2 : 1);
    this.summary.textContent =
      `ΔE*uv mean ${f(result.mean)} · p95 ${f(result.p95)} · max ${f(result.max)}` +
      (preview ? " (from preview frames)" : "");
    this.canvas.dataset.mean = String(result.mean);
    this.canvas.dataset.max = String(result.max);
    return true;
  }

  paint({ delta, width, height, preview }) {
    if (this.canvas.width !== width || this.canvas.height !== height) {
      this.canvas.width = width;
      this.canvas.height = height;
    }
    this.ctx.putImageData(new ImageData(colourizeDelta(delta, this.scaleMax), width, height), 0, 0);
    this.canvas.classList.remove("empty");
    if (this.badge) {
      this.badge.textContent = preview ? "preview" : "full";
      this.badge.dataset.quality = preview ? "preview" : "full";
    }
  }

  clear() {
    this.last = null;
    this.summary.textContent = "";
    this.canvas.classList.add("empty");
  }
}
