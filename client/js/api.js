// The only module that talks to the server: REST calls through fetch, and the render stream
// over a WebSocket. Every failure becomes an ApiError whose message a person can read.

/** A failed request, in words. `status` is the HTTP status (0 when the server was unreachable). */
export class ApiError extends Error {
  constructor(message, { status = 0, detail = null, retryAfterS = null, kind = "http" } = {}) {
    super(message);
    this.name = "ApiError";
    this.status = status;
    this.detail = detail;
    this.retryAfterS = retryAfterS;
    /** "http", "unreachable" or "aborted". */
    this.kind = kind;
  }
}

/** Turn FastAPI's `detail` (a string, or a list of pydantic errors) into one readable line. */
export function describeDetail(detail) {
  if (detail == null) return "";
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) {
    return detail
      .map((item) => {
        if (item && typeof item === "object" && "msg" in item) {
          const loc = Array.isArray(item.loc) ? item.loc.filter((p) => p !== "query" && p !== "body") : [];
          return loc.length ? `${loc.join(".")}: ${item.msg}` : item.msg;
        }
        return String(item);
      })
      .join("; ");
  }
  if (typeof detail === "object" && "msg" in detail) return String(detail.msg);
  return JSON.stringify(detail);
}

function parseRetryAfter(value) {
  if (!value) return null;
  const seconds = Number(value);
  if (Number.isFinite(seconds)) return Math.max(0, seconds);
  const date = Date.parse(value);
  return Number.isFinite(date) ? Math.max(0, (date - Date.now()) / 1000) : null;
}

async function errorFromResponse(response, what) {
  let detail = null;
  try {
    const body = await response.json();
    detail = body && "detail" in body ? body.detail : body;
  } catch {
    detail = response.statusText || null;
  }
  const text = describeDetail(detail);
  const retryAfterS = parseRetryAfter(response.headers.get("Retry-After"));
  let message;
  if (response.status === 404) message = `${what}: not found${text ? ` (${text})` : ""}`;
  else if (response.status === 503) message = `Server busy${text ? `: ${text}` : ""}`;
  else if (response.status === 429) message = `Rate limited${text ? `: ${text}` : ""}`;
  else message = `${what} failed (HTTP ${response.status})${text ? `: ${text}` : ""}`;
  return new ApiError(message, { status: response.status, detail, retryAfterS });
}

async function request(url, what, { signal, accept, method = "GET", json } = {}) {
  let response;
  const headers = accept ? { Accept: accept } : {};
  const init = { signal, method, headers };
  if (json !== undefined) {
    headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(json);
  }
  try {
    response = await fetch(url, init);
  } catch (err) {
    if (err && err.name === "AbortError") throw new ApiError(`${what}: cancelled`, { kind: "aborted" });
    throw new ApiError("Server unreachable: no answer from " + new URL(url, location.href).host, {
      kind: "unreachable",
    });
  }
  if (!response.ok) throw await errorFromResponse(response, what);
  return response;
}

async function getJson(url, what, options) {
  const response = await request(url, what, { ...options, accept: "application/json" });
  return response.json();
}

/** GET /api/health */
export function getHealth(options) {
  return getJson("/api/health", "Health check", options);
}

/** GET /api/ready: resolves when the server has loaded its scenes; 503 (ApiError) while loading. */
export function getReady(options) {
  return getJson("/api/ready", "Readiness check", options);
}

/** GET /api/scenes -> [{id, title, kind, params}] */
export function listScenes(options) {
  return getJson("/api/scenes", "Scene list", options);
}

/** GET /api/limits -> {max_side, max_full_pixels, max_preview_pixels}: the largest frames served. */
export function getLimits(options) {
  return getJson("/api/limits", "Limits", options);
}

/** GET /api/scenes/{id} -> {id, title, kind, params, camera, bbox, image_size, training} */
export function getScene(sceneId, options) {
  return getJson(`/api/scenes/${encodeURIComponent(sceneId)}`, `Scene '${sceneId}'`, options);
}

/**
 * The GET render URL of one frame (usable as an <img src> or a download link).
 * @param {string} sceneId
 * @param {{camera: {azimuth:number, elevation:number, distance:number}, fovDeg?:number|null,
 *          viewHeight?:number|null, width:number, height:number, params: Object<string, number>,
 *          quality?: "preview"|"full", format?: "png"|"jpeg"|"webp"}} req  (a viewHeight asks for an
 *          orthographic frame, a fovDeg for a perspective one)
 */
export function renderUrl(sceneId, req) {
  const query = new URLSearchParams({
    azimuth: String(req.camera.azimuth),
    elevation: String(req.camera.elevation),
    distance: String(req.camera.distance),
    ...Object.fromEntries(Object.entries(lensFields(req)).map(([k, v]) => [k, String(v)])),
    width: String(req.width),
    height: String(req.height),
    quality: req.quality || "full",
    format: req.format || "png",
  });
  for (const [name, value] of Object.entries(req.params || {})) query.set(name, String(value));
  return `/api/scenes/${encodeURIComponent(sceneId)}/render?${query}`;
}

/** The lens of a request as the API names it: {projection, fov_deg} or {projection, view_height}. */
export function lensFields(req) {
  if (Number.isFinite(req.viewHeight)) return { projection: "orthographic", view_height: req.viewHeight };
  return { projection: "perspective", fov_deg: req.fovDeg };
}

/**
 * Render one frame over HTTP. Each `Renderer` cancels its previous request when a new one
 * starts, so a slow stale frame never competes with the current one.
 */
export class HttpRenderer {
  constructor(sceneId) {
    this.sceneId = sceneId;
    this.controller = null;
  }

  /** @returns {Promise<{blob: Blob, renderMs: number|null}>} */
  async render(req) {
    this.cancel();
    const controller = new AbortController();
    this.controller = controller;
    try {
      const response = await request(renderUrl(this.sceneId, req), "Render", { signal: controller.signal });
      const blob = await response.blob();
      const header = response.headers.get("X-Render-Time-Ms");
      return { blob, renderMs: header != null && header !== "" ? Number(header) : null };
    } catch (err) {
      if (err && err.name === "AbortError") throw new ApiError("Render: cancelled", { kind: "aborted" });
      throw err;
    } finally {
      if (this.controller === controller) this.controller = null;
    }
  }

  cancel() {
    if (this.controller) this.controller.abort();
    this.controller = null;
  }
}

/** Fetch a full-quality image (for "save as PNG") as a Blob. */
export async function fetchImage(sceneId, req, options) {
  const response = await request(renderUrl(sceneId, req), "Render", options);
  return response.blob();
}

/**
 * POST /api/scenes/{id}/movies: start rendering a movie of a camera path.
 * @param {{path: object, fps: number, width: number, height: number, format: "mp4"|"gif",
 *          quality: "full"|"preview"}} job
 * @returns {Promise<{job_id: string, frames: number, status_url: string, file_url: string}>}
 */
export async function createMovie(sceneId, job, options) {
  const url = `/api/scenes/${encodeURIComponent(sceneId)}/movies`;
  const response = await request(url, "Movie", { ...options, method: "POST", json: job, accept: "application/json" });
  return response.json();
}

/** GET /api/movies/{job} -> {state, frames_done, frames_total, error, frames_per_second, seconds_left} */
export function getMovieStatus(statusUrl, options) {
  return getJson(statusUrl, "Movie status", options);
}

/** DELETE /api/movies/{job}: cancel a queued or running movie. */
export async function cancelMovie(statusUrl, options) {
  await request(statusUrl, "Cancelling the movie", { ...options, method: "DELETE", accept: "application/json" });
}

/** The status URL of a movie job (the server also returns it as `status_url`). */
export function movieStatusUrl(jobId) {
  return `/api/movies/${encodeURIComponent(jobId)}`;
}

const MIME = { png: "image/png", jpeg: "image/jpeg", webp: "image/webp" };

/**
 * WS /api/scenes/{id}/stream with automatic reconnection (exponential backoff with jitter).
 *
 * Callbacks:
 *   onFrame({seq, blob, renderMs, width, height, format, dropped})
 *   onError({seq, status, detail, message, retryAfterS})
 *   onOpen()                     the stream is (again) ready for requests
 *   onClose({code, reason, retryInS, gone})   gone: the scene no longer exists (close 4404)
 */
export class RenderStream {
  constructor(sceneId, callbacks, { minBackoffMs = 250, maxBackoffMs = 8000 } = {}) {
    this.sceneId = sceneId;
    this.callbacks = callbacks;
    this.minBackoffMs = minBackoffMs;
    this.maxBackoffMs = maxBackoffMs;
    this.attempt = 0;
    this.ws = null;
    this.header = null;
    this.closedByUs = false;
    this.reconnectTimer = null;
    this.connect();
  }

  get isOpen() {
    return this.ws !== null && this.ws.readyState === WebSocket.OPEN;
  }

  connect() {
    this.reconnectTimer = null;
    const scheme = location.protocol === "https:" ? "wss:" : "ws:";
    const url = `${scheme}//${location.host}/api/scenes/${encodeURIComponent(this.sceneId)}/stream`;
    let ws;
    try {
      ws = new WebSocket(url);
    } catch {
      this.scheduleReconnect(1006, "could not open");
      return;
    }
    ws.binaryType = "blob";
    this.ws = ws;
    this.header = null;
    ws.onopen = () => {
      this.attempt = 0;
      this.callbacks.onOpen?.();
    };
    ws.onmessage = (event) => this.handleMessage(event.data);
    ws.onclose = (event) => {
      if (this.ws !== ws) return;
      this.ws = null;
      if (this.closedByUs) return;
      if (event.code === 4404) {
        this.callbacks.onClose?.({ code: event.code, reason: event.reason, retryInS: null, gone: true });
        return;
      }
      this.scheduleReconnect(event.code, event.reason);
    };
  }

  scheduleReconnect(code, reason) {
    const base = Math.min(this.maxBackoffMs, this.minBackoffMs * 2 ** this.attempt);
    const delay = base * (0.75 + 0.5 * Math.random());
    this.attempt += 1;
    this.callbacks.onClose?.({ code, reason, retryInS: delay / 1000, gone: false });
    this.reconnectTimer = setTimeout(() => this.connect(), delay);
  }

  handleMessage(data) {
    if (typeof data === "string") {
      let msg;
      try {
        msg = JSON.parse(data);
      } catch {
        return;
      }
      if (msg.type === "frame") {
        this.header = msg;
      } else if (msg.type === "error") {
        this.header = null;
        const retryAfterS = Number.isFinite(Number(msg.retry_after)) ? Number(msg.retry_after) : null;
        this.callbacks.onError?.({
          seq: msg.seq,
          status: msg.status,
          detail: msg.detail,
          message: describeDetail(msg.detail),
          retryAfterS,
        });
      }
      return;
    }
    const header = this.header;
    this.header = null;
    if (!header) return; // binary without its header: cannot tell which request it answers
    const type = MIME[header.format] || "";
    const blob = data instanceof Blob ? (type ? new Blob([data], { type }) : data) : new Blob([data], { type });
    this.callbacks.onFrame?.({
      seq: header.seq,
      blob,
      renderMs: header.render_ms,
      width: header.width,
      height: header.height,
      format: header.format,
      dropped: header.dropped || 0,
    });
  }

  /** Send one render request; false when the socket is not open (the caller falls back to HTTP). */
  send(seq, req) {
    if (!this.isOpen) return false;
    this.ws.send(
      JSON.stringify({
        seq,
        camera: {
          azimuth: req.camera.azimuth,
          elevation: req.camera.elevation,
          distance: req.camera.distance,
        },
        ...lensFields(req),
        width: req.width,
        height: req.height,
        params: req.params,
        quality: req.quality,
        format: req.format,
      }),
    );
    return true;
  }

  /** Reconnect now (skipping the backoff wait), e.g. after the user asked to retry. */
  reconnectNow() {
    if (this.ws || this.closedByUs) return;
    clearTimeout(this.reconnectTimer);
    this.connect();
  }

  close() {
    this.closedByUs = true;
    clearTimeout(this.reconnectTimer);
    if (this.ws) this.ws.close(1000, "client closed");
    this.ws = null;
  }
}
