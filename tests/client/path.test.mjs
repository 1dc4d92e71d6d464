// Unit checks of client/js/path.js and splines.js: the same frames as the server's interpolation
// (model/visnerf/animation/interpolation.py), no jumps over the poles or across azimuth 180,
// parameters inside their ranges, the frame times of a movie, the document checks, editing and
// the URL form.
import assert from "node:assert/strict";
import { test } from "node:test";

import {
  cameraAt,
  frameCount,
  frameTimes,
  moveKeyframe,
  nextKeyframeTime,
  normalizePath,
  paramsAt,
  PathError,
  pathFromQuery,
  pathToQueryEntries,
  retimeKeyframe,
} from "../../client/js/path.js";
import { angleBetween, anglesToDirection, pchip } from "../../client/js/splines.js";
import { ViewState } from "../../client/js/state.js";

const AXES = [
  { name: "iso", min: 0.2, max: 0.8, default: 0.5 },
  { name: "time", min: 0, max: 1, default: 0 },
];
const SCENE_CAMERA = { azimuth: 0, elevation: 0, distance: 2, fov: 30 };

function path(cameras, { camera = "smooth", params = "linear", times = null, values = null } = {}) {
  return normalizePath(
    {
      version: 1,
      camera_interpolation: camera,
      param_interpolation: params,
      keyframes: cameras.map(([azimuth, elevation, distance = 2, fov = 30], i) => ({
        time: times ? times[i] : 2 * i,
        camera: { azimuth, elevation, distance, fov },
        params: values ? values[i] : {},
      })),
    },
    AXES,
    SCENE_CAMERA,
  );
}

function directionAt(p, t) {
  const c = cameraAt(p, t);
  return anglesToDirection(c.azimuth, c.elevation);
}

/** Largest angle (degrees) the view direction turns between samples `dt` apart over the path. */
function largestStepDeg(p, dt = 0.01) {
  const end = p.keyframes.at(-1).time;
  let previous = directionAt(p, p.keyframes[0].time);
  let largest = 0;
  for (let t = p.keyframes[0].time + dt; t <= end + 1e-9; t += dt) {
    const d = directionAt(p, t);
    largest = Math.max(largest, angleBetween(previous, d) * (180 / Math.PI));
    previous = d;
  }
  return largest;
}

const close = (a, b, tol, what) => assert.ok(Math.abs(a - b) <= tol, `${what}: ${a} vs ${b}`);

test("the same frames as the server's interpolation (golden values from interpolation.py)", () => {
  // sample_frames(parse_path(doc, axes, camera), fps=4, axes): the unit vector c2w[:3, 3] / distance,
  // the distance, fov_deg and the parameters of every frame (Python, float64, 9 decimals).
  const doc = {
    version: 1,
    camera_interpolation: "smooth",
    param_interpolation: "smooth",
    keyframes: [
      { time: 0, camera: { azimuth: 150, elevation: 10, distance: 2, fov: 30 }, params: { iso: 0.2 } },
      { time: 1, camera: { azimuth: -160, elevation: 40, distance: 3, fov: 40 }, params: { iso: 0.8, time: 1 } },
      { time: 2.5, camera: { azimuth: -90, elevation: -20, distance: 2.5, fov: 35 }, params: { iso: 0.3, time: 0.5 } },
      { time: 3, camera: { azimuth: 0, elevation: 85, distance: 1.5, fov: 30 }, params: { iso: 0.6 } },
    ],
  };
  // [t, direction, distance, fov, iso, time]
  const golden = [
    [0.0, [0.492403877, 0.173648178, -0.852868532], 2.0, 30.0, 0.2, 0.0],
    [0.25, [0.324321643, 0.335466046, -0.884464812], 2.371875, 33.71875, 0.430625, 0.371875],
    [0.5, [0.140324295, 0.488665821, -0.86111254], 2.691666667, 36.916666667, 0.621666667, 0.691666667],
    [0.75, [-0.056716246, 0.600542893, -0.797578524], 2.915625, 39.15625, 0.751875, 0.915625],
    [1.0, [-0.26200263, 0.64278761, -0.71984631], 3.0, 40.0, 0.8, 1.0],
    [1.25, [-0.474497468, 0.610783435, -0.633873606], 2.985485485, 39.819023569, 0.762962963, 0.981902357],
    [1.5, [-0.596255297, 0.582888517, -0.552015034], 2.942442442, 39.30976431, 0.67037037, 0.930976431],
    [1.75, [-0.497206492, 0.464846439, -0.7326005], 2.871621622, 38.522727273, 0.55, 0.852272727],
    [2.0, [-0.651863051, -0.568839447, -0.501494014], 2.773773774, 37.508417508, 0.42962963, 0.750841751],
    [2.25, [-0.721720595, -0.676706351, -0.145560631], 2.64964965, 36.317340067, 0.337037037, 0.631734007],
    [2.5, [-0.939692621, -0.342020143, 0.0], 2.5, 35.0, 0.3, 0.5],
    [2.75, [-0.855368232, 0.510576277, 0.087504585], 2.110501126, 32.888257576, 0.397916667, 0.288825758],
    [3.0, [0.0, 0.996194698, 0.087155743], 1.5, 30.0, 0.6, 0.0],
  ];
  const p = normalizePath(doc, AXES, SCENE_CAMERA);
  const times = frameTimes(p, 4);
  assert.equal(times.length, golden.length);
  golden.forEach(([t, dir, distance, fov, iso, time], i) => {
    close(times[i], t, 1e-12, "frame time");
    const c = cameraAt(p, t);
    anglesToDirection(c.azimuth, c.elevation).forEach((x, j) => close(x, dir[j], 1e-8, `direction at ${t}`));
    close(c.distance, distance, 1e-8, `distance at ${t}`);
    close(c.fov, fov, 1e-8, `fov at ${t}`);
    const values = paramsAt(p, t, AXES);
    close(values.iso, iso, 1e-8, `iso at ${t}`);
    close(values.time, time, 1e-8, `time at ${t}`);
  });
});

test("linear: slerp over the pole, no jump and no detour", () => {
  // (az 0, el 60) to (az 180, el 60): the shortest way is over the north pole (60 degrees of arc).
  const p = path([[0, 60], [180, 60]], { camera: "linear" });
  const mid = directionAt(p, 1);
  mid.forEach((x, j) => close(x, [0, 1, 0][j], 1e-9, "the midpoint is the pole"));
  // 200 samples over 60 degrees at constant speed: 0.3 degrees each (2 s, 0.01 s apart).
  close(largestStepDeg(p), 0.3, 1e-6, "largest step");
  // The azimuth flips at the pole (that is what over the pole means), the direction does not.
  assert.equal(Math.round(cameraAt(p, 0.9).azimuth), 0);
  assert.equal(Math.round(cameraAt(p, 1.1).azimuth), 180);
});

test("across azimuth 180 the short way round, both interpolations", () => {
  for (const camera of ["linear", "smooth"]) {
    const p = path([[170, 0], [-170, 0], [-150, 0]], { camera });
    for (let t = 0; t <= 2; t += 0.05) {
      const { azimuth, elevation } = cameraAt(p, t);
      assert.ok(Math.abs(azimuth) >= 169.999, `${camera}: azimuth ${azimuth} at ${t} s went the long way`);
      close(elevation, 0, 1e-9, `${camera}: stays on the equator`);
    }
    // 20 degrees in 2 s on one great circle: 0.1 degree per 0.01 s, without jumps.
    assert.ok(largestStepDeg(p) < 0.11, `${camera}: a jump of ${largestStepDeg(p)} degrees`);
  }
});

test("smooth: passes every keyframe and stays continuous through the pole", () => {
  const p = path([[0, 45], [180, 45], [180, 0], [90, -30]], { camera: "smooth" });
  for (const kf of p.keyframes) {
    const c = cameraAt(p, kf.time);
    assert.deepEqual(c, kf.camera);
    // Just after a keyframe, the camera is near it.
    const d = angleBetween(directionAt(p, kf.time + 1e-4), anglesToDirection(kf.camera.azimuth, kf.camera.elevation));
    assert.ok(d < 1e-3, `jump after the keyframe at ${kf.time} s`);
  }
  assert.ok(largestStepDeg(p) < 1.5, `a jump of ${largestStepDeg(p)} degrees`);
  const top = Math.max(...Array.from({ length: 201 }, (_, i) => cameraAt(p, i * 0.01).elevation));
  assert.ok(top > 89, "the path goes over the pole");
});

test("distance and fov: linear, or monotone (never past the keyframe values) when smooth", () => {
  const lin = path([[0, 0, 2, 30], [0, 0, 4, 50]], { camera: "linear" });
  assert.equal(cameraAt(lin, 1).distance, 3);
  assert.equal(cameraAt(lin, 1).fov, 40);
  const smooth = path([[0, 0, 2], [10, 0, 4], [20, 0, 4.1], [30, 0, 1]], { camera: "smooth" });
  for (let t = 0; t <= 6; t += 0.05) {
    const d = cameraAt(smooth, t).distance;
    assert.ok(d >= 1 - 1e-12 && d <= 4.1 + 1e-12, `distance ${d} at ${t} s`);
  }
  assert.equal(pchip([0, 1, 2], [0, 1, 1], 1.5), 1, "flat where the data are flat");
});

test("parameters: interpolated, eased without overshoot, clamped, defaults for missing ones", () => {
  const values = [{ iso: 0.2 }, { iso: 0.8, time: 1 }, { iso: 0.3 }];
  const lin = path([[0, 0], [0, 0], [0, 0]], { values });
  assert.deepEqual(paramsAt(lin, 1, AXES), { iso: 0.5, time: 0.5 });
  assert.deepEqual(paramsAt(lin, 0, AXES), { iso: 0.2, time: 0 }, "time takes the axis default 0");
  assert.deepEqual(paramsAt(lin, 99, AXES), { iso: 0.3, time: 0 }, "held after the last keyframe");
  const eased = path([[0, 0], [0, 0], [0, 0]], { values, params: "smooth" });
  for (let t = 0; t <= 4; t += 0.05) {
    const v = paramsAt(eased, t, AXES);
    assert.ok(v.iso >= 0.2 && v.iso <= 0.8 && v.time >= 0 && v.time <= 1, `${JSON.stringify(v)} at ${t} s`);
  }
  // A path built by hand (not checked) with values outside the range: the samples are clamped.
  const raw = { ...lin, keyframes: lin.keyframes.map((k, i) => ({ ...k, params: { iso: [-1, 5, 0.5][i] } })) };
  assert.equal(paramsAt(raw, 0, AXES).iso, 0.2);
  assert.equal(paramsAt(raw, 2, AXES).iso, 0.8);
  // A document with a value outside the range is refused, naming the field (as the server does);
  // float32 rounding at an end is let through and clamped.
  assert.throws(() => path([[0, 0]], { values: [{ iso: 3 }] }), /keyframes\[0\]\.params\.iso: must be in \[0\.2, 0\.8\], got 3/);
  assert.equal(path([[0, 0]], { values: [{ iso: 0.8000001 }] }).keyframes[0].params.iso, 0.8);
});

test("frame count and frame times follow the server (round(duration * fps) + 1)", () => {
  const p = path([[0, 0], [90, 0]], { times: [0, 1] });
  assert.equal(frameCount(p, 4), 5);
  assert.deepEqual(frameTimes(p, 4), [0, 0.25, 0.5, 0.75, 1]);
  assert.equal(frameCount(path([[0, 0]]), 30), 1, "one keyframe, one frame");
  const late = path([[0, 0], [90, 0]], { times: [1, 2.5] });
  assert.deepEqual(frameTimes(late, 2), [1, 1.5, 2, 2.5], "times start at the first keyframe");
  // Python rounds halves to even: 0.5 s at 5 fps is 2.5 -> 2 intervals, 1.5 s at 1 fps -> 2.
  assert.equal(frameCount(path([[0, 0], [9, 0]], { times: [0, 0.5] }), 5), 3);
  assert.equal(frameCount(path([[0, 0], [9, 0]], { times: [0, 1.5] }), 1), 3);
  // The frame after the last keyframe would hold it: the last frame time is the path's end.
  assert.deepEqual(cameraAt(p, 1.0000001), p.keyframes[1].camera);
});

test("document checks name the field, like the server's", () => {
  const ok = { version: 1, keyframes: [{ time: 0, camera: { azimuth: 1, elevation: 2, distance: 3, fov: 40 } }] };
  const bad = (change, pattern) => {
    const doc = structuredClone(ok);
    change(doc);
    assert.throws(() => normalizePath(doc, AXES, SCENE_CAMERA), (err) => err instanceof PathError && pattern.test(err.message));
  };
  const clean = normalizePath(ok, AXES, SCENE_CAMERA);
  assert.equal(clean.camera_interpolation, "smooth");
  assert.equal(clean.param_interpolation, "linear");
  assert.deepEqual(clean.keyframes[0].params, { iso: 0.5, time: 0 });
  const partial = normalizePath({ version: 1, keyframes: [{ time: 0, camera: { azimuth: 90 } }] }, AXES, SCENE_CAMERA);
  assert.deepEqual(partial.keyframes[0].camera, { azimuth: 90, elevation: 0, distance: 2, fov: 30 });
  bad((d) => (d.version = 2), /^version: must be 1/);
  bad((d) => delete d.version, /^version: missing/);
  bad((d) => (d.extra = 1), /^extra: unknown key/);
  bad((d) => (d.camera_interpolation = "cubic"), /^camera_interpolation: must be one of/);
  bad((d) => (d.keyframes = []), /^keyframes: must hold at least one keyframe/);
  bad((d) => (d.keyframes[0].camera.elevation = 120), /^keyframes\[0\]\.camera\.elevation: must be in \[-90, 90\], got 120/);
  bad((d) => (d.keyframes[0].camera.distance = 0), /^keyframes\[0\]\.camera\.distance: must be above 0/);
  bad((d) => (d.keyframes[0].camera.fov = "30"), /^keyframes\[0\]\.camera\.fov: must be a number, got a string/);
  bad((d) => (d.keyframes[0].thumbnail = "x"), /^keyframes\[0\]\.thumbnail: unknown key/);
  bad((d) => (d.keyframes[0].params = { pressure: 1 }), /^keyframes\[0\]\.params\.pressure: unknown parameter/);
  bad((d) => (d.keyframes[0].time = -1), /^keyframes\[0\]\.time: must be >= 0/);
  bad((d) => d.keyframes.push({ ...d.keyframes[0] }), /^keyframes\[1\]\.time: must be after keyframes\[0\]\.time/);
});

test("editing: new keyframes 2 s apart, moves keep the time slots, retiming re-sorts", () => {
  const p = path([[10, 0], [20, 0], [30, 0]]);
  assert.deepEqual(p.keyframes.map((k) => k.time), [0, 2, 4]);
  assert.equal(nextKeyframeTime(p), 6);
  const moved = moveKeyframe(p, 0, +1);
  assert.deepEqual(moved.keyframes.map((k) => [k.time, k.camera.azimuth]), [[0, 20], [2, 10], [4, 30]]);
  assert.deepEqual(moveKeyframe(p, 0, -1).keyframes, p.keyframes, "nothing before the first");
  const retimed = retimeKeyframe(p, 0, 3);
  assert.deepEqual(retimed.keyframes.map((k) => [k.time, k.camera.azimuth]), [[2, 20], [3, 10], [4, 30]]);
  assert.throws(() => retimeKeyframe(p, 0, 2), PathError);
  assert.throws(() => retimeKeyframe(p, 0, -1), PathError);
  assert.throws(() => retimeKeyframe(p, 0, NaN), PathError);
});

test("URL form: compact, round trip, refusals", () => {
  const p = path([[12.345678, -7.5, 2.123456, 30], [-170, 89.9, 3, 45]], {
    camera: "linear",
    values: [{ iso: 0.25 }, { iso: 0.75, time: 0.125 }],
  });
  const entries = pathToQueryEntries(p, ["iso", "time"]);
  assert.deepEqual(entries, [
    ["kf", "0_12.35_-7.5_2.1235_30_0.25_0"],
    ["kf", "2_-170_89.9_3_45_0.75_0.125"],
    ["kfi", "ll"],
  ]);
  const query = new URLSearchParams(entries);
  assert.ok(!/%/.test(query.toString()), `readable in the address bar: ${query}`);
  const back = pathFromQuery(query, AXES, SCENE_CAMERA);
  assert.equal(back.camera_interpolation, "linear");
  assert.deepEqual(back.keyframes[1], p.keyframes[1]);
  close(back.keyframes[0].camera.azimuth, p.keyframes[0].camera.azimuth, 0.005, "azimuth to 2 decimals");
  assert.equal(pathFromQuery(new URLSearchParams("scene=x"), AXES), null, "no kf: no path");
  assert.deepEqual(pathToQueryEntries(path([[0, 0]]), ["iso", "time"]).map(([k]) => k), ["kf"], "default modes: no kfi");
  assert.throws(() => pathFromQuery(new URLSearchParams("kf=0_1_2"), AXES), /keyframe 1: 3 fields, expected 7/);
  assert.throws(() => pathFromQuery(new URLSearchParams("kf=0_a_0_2_30__"), AXES), /keyframes\[0\]\.camera\.azimuth/);
  assert.throws(() => pathFromQuery(new URLSearchParams("kf=0_0_0_2_30__&kf=0_0_0_2_30__"), AXES), /must be after/);
  assert.throws(() => pathFromQuery(new URLSearchParams("kf=0_0_0_2_30__&kfi=xx"), AXES), /kfi/);
  // An empty field leaves the parameter to its default.
  assert.deepEqual(pathFromQuery(new URLSearchParams("kf=0_0_0_2_30__"), AXES).keyframes[0].params, { iso: 0.5, time: 0 });
});

test("the view state carries the path in its URL; a malformed one is left out with a reason", () => {
  const scene = {
    id: "tiny",
    kind: "dvr",
    params: AXES.map((a) => ({ ...a, values: [a.min, a.max] })),
    camera: { azimuth: 30, elevation: 20, distance: 2.5, fov_deg: 30 },
    image_size: [64, 64],
  };
  const a = new ViewState();
  a.setScene(structuredClone(scene));
  a.setPath(path([[10, 20, 2.5, 30], [40, 50, 3, 30]], { values: [{ iso: 0.3 }, { iso: 0.6 }] }));
  const query = a.toQuery();
  assert.equal(query.getAll("kf").length, 2);
  const b = new ViewState();
  b.setScene(structuredClone(scene));
  b.applyQuery(query);
  assert.deepEqual(b.path, a.path);
  assert.equal(b.pathWarning, null);
  const broken = new URLSearchParams(query);
  broken.append("kf", "oops");
  b.applyQuery(broken);
  assert.equal(b.path.keyframes.length, 0);
  assert.match(b.pathWarning, /keyframe 3/);
  b.setScene(structuredClone(scene));
  assert.equal(b.path.keyframes.length, 0, "a new scene starts without a path");
});

test("orthographic paths: view heights read, interpolated and written, one projection per path", () => {
  const ortho = { azimuth: 0, elevation: 0, distance: 2.5, fov: 30, view_height: 1.4 };
  const doc = (...cameras) => ({ version: 1, keyframes: cameras.map((camera, i) => ({ time: i, camera })) });
  const p = normalizePath(doc({ azimuth: 0, view_height: 1 }, { azimuth: 40, view_height: 2 }), AXES, SCENE_CAMERA);
  assert.deepEqual(p.keyframes[0].camera, { azimuth: 0, elevation: 0, distance: 2, view_height: 1 });
  close(cameraAt({ ...p, camera_interpolation: "linear" }, 0.5).view_height, 1.5, 1e-12, "linear view height");
  assert.ok(!("fov" in cameraAt(p, 0.5)), "an orthographic path has no field of view");
  // Keyframes without a lens take the scene's, in the path's projection (as parse.py does).
  const own = normalizePath(doc({ azimuth: 0 }, { azimuth: 90 }), AXES, ortho);
  assert.deepEqual(own.keyframes.map((k) => k.camera.view_height), [1.4, 1.4]);
  const named = normalizePath(doc({ fov: 20 }, {}), AXES, ortho);
  close(named.keyframes[1].camera.fov, (360 / Math.PI) * Math.atan(0.7 / 2.5), 1e-12, "the fov framing it alike");
  assert.throws(() => normalizePath(doc({ fov: 30 }, { view_height: 1 }), AXES, ortho),
    /keyframes\[1\]\.camera\.view_height: keyframes\[0\] has a fov; a path keeps one projection/);
  assert.throws(() => normalizePath(doc({ fov: 30, view_height: 1 }), AXES, ortho), /not both/);
  assert.throws(() => normalizePath(doc({ view_height: -1 }), AXES, ortho), /view_height: must be above 0/);
  // The URL form: "h" and the view height in the lens field.
  const entries = pathToQueryEntries(p, ["iso", "time"]);
  assert.deepEqual(entries.map(([, v]) => v.split("_")[4]), ["h1", "h2"]);
  assert.deepEqual(pathFromQuery(new URLSearchParams(entries), AXES, SCENE_CAMERA).keyframes, p.keyframes);
});
