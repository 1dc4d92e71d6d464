// Unit checks of client/js/frames.js: the newest frame wins, previews are throttled, the full
// frame follows the input. The WebSocket and the canvas are replaced by small fakes.
import assert from "node:assert/strict";
import { test } from "node:test";

class FakeSocket {
  static CONNECTING = 0;
  static OPEN = 1;
  static last = null;
  constructor(url) {
    this.url = url;
    this.readyState = FakeSocket.OPEN;
    this.sent = [];
    FakeSocket.last = this;
    setTimeout(() => this.onopen?.(), 0);
  }
  send(text) {
    this.sent.push(JSON.parse(text));
  }
  close() {}
}
globalThis.WebSocket = FakeSocket;
globalThis.location = { protocol: "http:", host: "example.test", href: "http://example.test/" };
globalThis.requestAnimationFrame = (fn) => setTimeout(fn, 0);
globalThis.cancelAnimationFrame = (id) => clearTimeout(id);

const { FrameChannel, RenderScheduler } = await import("../../client/js/frames.js");

function fakeView() {
  const drawn = [];
  return {
    drawn,
    canvas: { width: 0, height: 0 },
    shown: null,
    // Decoding takes longer for bigger "images", so frames can finish out of order.
    decode: (blob) => new Promise((resolve) => setTimeout(() => resolve({ close() {}, blob }), blob.delayMs || 0)),
    draw(bitmap, meta) {
      drawn.push(meta.seq);
      this.shown = meta;
    },
  };
}

function makeChannel(view) {
  const shown = [];
  const errors = [];
  const stats = { record: (entry) => entry };
  const channel = new FrameChannel({
    name: "A",
    sceneId: "tiny",
    view,
    stats,
    onShown: (frame) => shown.push(frame),
    onError: (err) => errors.push(err),
    onConnection: () => {},
  });
  return { channel, shown, errors };
}

const req = (quality = "preview") => ({
  camera: { azimuth: 0, elevation: 0, distance: 2 },
  fovDeg: 30,
  width: 32,
  height: 32,
  params: {},
  quality,
  format: quality === "full" ? "png" : "jpeg",
});

const tick = (ms = 5) => new Promise((resolve) => setTimeout(resolve, ms));

test("a frame older than the one on screen is never drawn", async () => {
  const view = fakeView();
  const { channel } = makeChannel(view);
  await tick();
  const s1 = channel.request(req(), 0);
  const s2 = channel.request(req(), 1);
  const s3 = channel.request(req("full"), 2);
  assert.deepEqual(FakeSocket.last.sent.map((m) => m.seq), [s1, s2, s3]);
  await channel.receive({ seq: s3, blob: {}, renderMs: 5 });
  await channel.receive({ seq: s1, blob: {}, renderMs: 5 }); // late
  await channel.receive({ seq: s2, blob: {}, renderMs: 5 }); // late
  assert.deepEqual(view.drawn, [s3]);
  channel.close();
});

test("when decodes finish out of order, the older frame is dropped", async () => {
  const view = fakeView();
  const { channel } = makeChannel(view);
  await tick();
  const s1 = channel.request(req(), 0);
  const s2 = channel.request(req(), 0);
  const slow = channel.receive({ seq: s1, blob: { delayMs: 30 }, renderMs: 5 });
  const fast = channel.receive({ seq: s2, blob: { delayMs: 0 }, renderMs: 5 });
  await Promise.all([slow, fast]);
  assert.deepEqual(view.drawn, [s2]);
  channel.close();
});

test("stream messages: header then binary make one frame; errors are reported with their seq", async () => {
  const view = fakeView();
  const { channel, errors } = makeChannel(view);
  await tick();
  const seq = channel.request(req("full"), 0);
  const ws = FakeSocket.last;
  ws.onmessage({ data: JSON.stringify({ type: "frame", seq, render_ms: 12, width: 32, height: 32, format: "png", dropped: 0 }) });
  ws.onmessage({ data: new Blob([new Uint8Array([1, 2, 3])]) });
  await tick(10);
  assert.deepEqual(view.drawn, [seq]);
  const bad = channel.request(req("full"), 0);
  ws.onmessage({ data: JSON.stringify({ type: "error", seq: bad, status: 422, detail: "time: out of range [0, 1]" }) });
  assert.equal(errors.length, 1);
  assert.equal(errors[0].status, 422);
  assert.match(errors[0].message, /out of range/);
  channel.close();
});

test("scheduler: previews while moving (at most two in flight), then one full PNG", async () => {
  const view = fakeView();
  const { channel } = makeChannel(view);
  await tick();
  let azimuth = 0;
  const scheduler = new RenderScheduler(
    channel,
    (quality) => ({ ...req(quality), camera: { azimuth, elevation: 0, distance: 2 } }),
    { idleMs: 40 },
  );
  const ws = FakeSocket.last;
  for (let i = 0; i < 10; i += 1) {
    azimuth += 1;
    scheduler.input(i);
    await tick(2);
  }
  const previews = ws.sent.filter((m) => m.quality === "preview");
  assert.equal(previews.length, 2, "no answers yet: only two previews may be in flight");
  assert.ok(previews.every((m) => m.format === "jpeg"));
  await channel.receive({ seq: previews[1].seq, blob: {}, renderMs: 3 });
  await tick(5);
  assert.equal(ws.sent.filter((m) => m.quality === "preview").length, 3, "an answer lets the newest state go");
  await tick(60);
  const full = ws.sent.filter((m) => m.quality === "full");
  assert.equal(full.length, 1);
  assert.equal(full[0].format, "png");
  assert.equal(full[0].camera.azimuth, 10);
  scheduler.stop();
  channel.close();
});
