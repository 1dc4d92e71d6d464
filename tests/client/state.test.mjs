// Unit checks of client/js/state.js (camera limits, parameter ranges, URL round trip).
import assert from "node:assert/strict";
import { test } from "node:test";

import { ELEVATION_LIMIT, ViewState, wrapAzimuth } from "../../client/js/state.js";

const SCENE = {
  id: "tiny",
  title: "Tiny",
  kind: "dvr",
  params: [
    { name: "time", min: 0, max: 1, values: [0, 0.5, 1], default: 0.5 },
    { name: "isovalue", min: 0.2, max: 0.8, values: [0.2, 0.8], default: 0.2 },
  ],
  camera: { azimuth: 30, elevation: 20, distance: 2.5, fov_deg: 30 },
  image_size: [64, 32],
};

function fresh() {
  const state = new ViewState();
  state.setScene(structuredClone(SCENE));
  return state;
}

test("azimuth wraps into [-180, 180)", () => {
  assert.equal(wrapAzimuth(0), 0);
  assert.equal(wrapAzimuth(180), -180);
  assert.equal(wrapAzimuth(-180), -180);
  assert.equal(wrapAzimuth(190), -170);
  assert.equal(wrapAzimuth(-190), 170);
  assert.equal(wrapAzimuth(720 + 45), 45);
});

test("scene defaults: camera and parameters", () => {
  const s = fresh();
  assert.deepEqual(s.camera, { azimuth: 30, elevation: 20, distance: 2.5 });
  assert.equal(s.fovDeg, 30);
  assert.deepEqual(s.params, { time: 0.5, isovalue: 0.2 });
});

test("orbit clamps the elevation at the poles and zoom to [0.3, 4] x default", () => {
  const s = fresh();
  s.orbit(0, 500);
  assert.equal(s.camera.elevation, ELEVATION_LIMIT);
  s.orbit(0, -1000);
  assert.equal(s.camera.elevation, -ELEVATION_LIMIT);
  s.orbit(200, 0);
  assert.equal(s.camera.azimuth, -130);
  s.zoom(100);
  assert.equal(s.camera.distance, 10);
  s.zoom(1e-6);
  assert.equal(s.camera.distance, 0.75);
  s.resetCamera();
  assert.deepEqual(s.camera, { azimuth: 30, elevation: 20, distance: 2.5 });
});

test("parameters stay inside their ranges; unknown names are ignored", () => {
  const s = fresh();
  assert.equal(s.setParam("time", 3), 1);
  assert.equal(s.setParam("isovalue", -1), 0.2);
  assert.equal(s.setParam("nope", 0.5), undefined);
  assert.equal(s.setParam("time", Number.NaN), undefined);
  assert.deepEqual(s.params, { time: 1, isovalue: 0.2 });
});

test("change events say what changed and whether it is interactive", () => {
  const s = fresh();
  const seen = [];
  s.addEventListener("change", (e) => seen.push([e.detail.type, e.detail.interactive]));
  s.orbit(1, 0);
  s.setParam("time", 0.7, { interactive: false });
  s.setParam("time", 0.7); // unchanged: no event
  s.setParam("isovalue", 0.5, { set: "B" });
  assert.deepEqual(seen, [
    ["camera", true],
    ["params", false],
    ["paramsB", true],
  ]);
});

test("URL round trip restores camera, parameters and comparison", () => {
  const s = fresh();
  s.setCamera({ azimuth: -120.25, elevation: 45.5, distance: 3 });
  s.setParam("time", 0.25);
  s.setParam("isovalue", 0.6125);
  s.setParam("time", 0.75, { set: "B" });
  s.setCompare(true);
  s.setResolution(384);
  const query = s.toQuery();
  assert.equal(query.get("scene"), "tiny");
  const t = fresh();
  t.applyQuery(new URLSearchParams(query.toString()));
  assert.deepEqual(t.camera, s.camera);
  assert.deepEqual(t.params, s.params);
  assert.deepEqual(t.paramsB, s.paramsB);
  assert.equal(t.compare, true);
  assert.equal(t.resolution, 384);
});

test("URL values out of range are clamped; junk is ignored", () => {
  const s = fresh();
  s.applyQuery(new URLSearchParams("az=270&el=-100&dist=99&time=abc&isovalue=9"));
  assert.deepEqual(s.camera, { azimuth: -90, elevation: -ELEVATION_LIMIT, distance: 10 });
  assert.deepEqual(s.params, { time: 0.5, isovalue: 0.8 });
});

test("frame size keeps the training aspect", () => {
  const s = fresh();
  s.setResolution(256);
  assert.deepEqual(s.frameSize(), { width: 256, height: 128 });
  assert.deepEqual(s.frameSize(0.5), { width: 128, height: 64 });
});

test("an orthographic scene starts orthographic; zoom scales the view height; switching keeps the framing", () => {
  const s = new ViewState();
  s.setScene({ ...structuredClone(SCENE), camera: { ...SCENE.camera, projection: "orthographic", view_height: 1.4 } });
  assert.equal(s.projection, "orthographic");
  assert.deepEqual(s.lens(), { projection: "orthographic", fovDeg: null, viewHeight: 1.4 });
  s.zoom(0.5);
  assert.equal(s.viewHeight, 0.7);
  assert.equal(s.camera.distance, 2.5, "an orthographic zoom leaves the camera where it is");
  s.zoom(0.01);
  assert.ok(Math.abs(s.viewHeight - 0.3 * 1.4) < 1e-12, "clamped to the zoom range");
  assert.deepEqual(s.keyframeCamera(), { azimuth: 30, elevation: 20, distance: 2.5, view_height: s.viewHeight });
  const query = s.toQuery();
  assert.equal(query.get("proj"), null, "the scene's own projection is not written");
  const t = new ViewState();
  t.setScene({ ...structuredClone(SCENE), camera: { ...SCENE.camera, projection: "orthographic", view_height: 1.4 } });
  t.applyQuery(new URLSearchParams(query.toString()));
  assert.ok(Math.abs(t.viewHeight - s.viewHeight) < 1e-4);
  // Perspective: the distance that frames the orbit centre alike at the scene's fov.
  s.setViewHeight(1.4);
  s.setProjection("perspective");
  assert.ok(Math.abs(s.camera.distance - 1.4 / (2 * Math.tan(Math.PI / 12))) < 1e-12);
  assert.equal(s.toQuery().get("proj"), "p");
  s.setProjection("orthographic");
  assert.ok(Math.abs(s.viewHeight - 1.4) < 1e-12, "and back");
  s.resetCamera();
  assert.deepEqual([s.projection, s.viewHeight, s.camera.distance], ["orthographic", 1.4, 2.5]);
  // A perspective scene: the orthographic lens it offers frames it alike from the default distance.
  const p = fresh();
  assert.equal(p.projection, "perspective");
  assert.ok(Math.abs(p.sceneViewHeight - 2 * 2.5 * Math.tan(Math.PI / 12)) < 1e-12);
});

test("frames at the view's size: the training aspect, within the server's limits, only when larger", () => {
  const s = fresh(); // trained 64x32
  s.setResolution(256);
  s.chooseResolution("screen");
  assert.equal(s.fitScreen, true);
  assert.deepEqual(s.frameSize(), { width: 256, height: 128 });
  assert.deepEqual(s.fullSize(), { width: 64, height: 32 }, "fitting the view: first the trained size");
  assert.deepEqual(s.screenSize({ width: 1400, height: 1000 }), { width: 1400, height: 700 });
  assert.deepEqual(s.screenSize({ width: 800, height: 1000 }), { width: 800, height: 400 });
  const limits = { max_side: 1024, max_full_pixels: 1920 * 1080 };
  assert.deepEqual(s.screenSize({ width: 4000, height: 4000 }, limits), { width: 1024, height: 512 });
  const pixels = s.screenSize({ width: 4000, height: 4000 }, { max_side: 8192, max_full_pixels: 400 * 200 });
  assert.ok(pixels.width * pixels.height <= 400 * 200 && pixels.width === 2 * pixels.height);
  assert.deepEqual(s.screenSize({ width: 200, height: 200 }), { width: 200, height: 100 });
  assert.equal(s.screenSize({ width: 60, height: 60 }), null, "not larger than the full frame");
  assert.equal(s.toQuery().get("res"), "screen");
  s.chooseResolution("384");
  assert.equal(s.fitScreen, false);
  assert.deepEqual(s.fullSize(), { width: 384, height: 192 }, "a chosen size is the full frame's");
  assert.equal(s.screenSize({ width: 1400, height: 1000 }), null, "a chosen size alone");
  const t = fresh();
  t.applyQuery(new URLSearchParams("res=screen"));
  assert.equal(t.fitScreen, true);
  t.applyQuery(new URLSearchParams("res=128"));
  assert.deepEqual([t.fitScreen, t.resolution], [false, 128]);
});
