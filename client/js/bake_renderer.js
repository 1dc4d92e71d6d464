// The browser's renderer: marches a bake (bake.js) in a WebGL2 fragment shader, the same samples
// and arithmetic as the CPU reference (model/visnerf/bake/bake_render.py): samples `step` apart
// from where the ray enters the box, the first half a step in; clear cells skipped, whole clear
// blocks of the coarse grid jumped; raw density and colour coefficients from the GPU's trilinear
// filtering; early termination once the transmittance is below the bake's epsilon.

import { COARSE_CELLS, denseBake, orbitFrame, textureBytes } from "./bake.js";

/** Largest GPU memory a bake may take before the client keeps to server frames. */
export const MAX_TEXTURE_BYTES = 768 * 1024 * 1024;
const MAX_STEPS = 8192;

const VERTEX = `#version 300 es
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}`;

function fragmentSource(layout) {
  const { textures, basis, shading, shDegree, powers } = layout;
  const samplers = Array.from({ length: textures }, (_, t) => `uniform highp sampler3D uCoef${t};`).join("\n");
  const fetches = Array.from({ length: textures }, (_, t) => `    vec4 c${t} = texture(uCoef${t}, tc);\n` +
    [0, 1, 2, 3].map((k) => (4 * t + k < 3 * basis ? `    coef[${4 * t + k}] = c${t}[${k}];` : "")).join("\n")).join("\n");
  const sh = ["b[0] = 0.28209479177387814;"];
  if (shDegree >= 1) sh.push("b[1] = -0.4886025119029199 * d.y;", "b[2] = 0.4886025119029199 * d.z;", "b[3] = -0.4886025119029199 * d.x;");
  if (shDegree >= 2) {
    sh.push(
      "b[4] = 1.0925484305920792 * d.x * d.y;", "b[5] = -1.0925484305920792 * d.y * d.z;",
      "b[6] = 0.31539156525252005 * (2.0 * d.z * d.z - d.x * d.x - d.y * d.y);",
      "b[7] = -1.0925484305920792 * d.x * d.z;", "b[8] = 0.5462742152960396 * (d.x * d.x - d.y * d.y);",
    );
  }
  const nSh = (shDegree + 1) ** 2;
  let level = "";
  if (shading === "level") {
    level = `
    vec3 g = vec3(0.0);
    g += rawAt(p + uNormalStep * vec3(1.0, 1.0, 1.0)) * vec3(1.0, 1.0, 1.0);
    g += rawAt(p + uNormalStep * vec3(1.0, -1.0, -1.0)) * vec3(1.0, -1.0, -1.0);
    g += rawAt(p + uNormalStep * vec3(-1.0, 1.0, -1.0)) * vec3(-1.0, 1.0, -1.0);
    g += rawAt(p + uNormalStep * vec3(-1.0, -1.0, 1.0)) * vec3(-1.0, -1.0, 1.0);
    float cosine = dot(g, d) / sqrt(dot(g, g) + 1e-12);
    float facing = clamp(cosine, 0.0, 1.0);
    b[${nSh}] = cosine;
${powers.map((p, i) => `    b[${nSh + 1 + i}] = pow(facing, ${p.toFixed(1)});`).join("\n")}`;
  }
  return `#version 300 es
precision highp float;
precision highp int;
precision highp sampler3D;
uniform highp sampler3D uRaw;
uniform highp sampler3D uCells;
uniform highp sampler3D uCoarse;
${samplers}
uniform vec2 uSize;
uniform vec4 uLens;       // fx, fy, cx, cy (pixels; pixels per world unit when orthographic)
uniform bool uOrtho;
uniform vec3 uRight, uUp, uBack, uEye;
uniform vec3 uLo, uHi;
uniform vec3 uGrid;        // vertices per axis
uniform vec3 uCoarseDims;  // blocks per axis
uniform float uStep, uScale, uEps, uNormalStep;
uniform vec3 uBackground;
out vec4 outColour;

float rawAt(vec3 p) {
  vec3 g = (p - uLo) / (uHi - uLo) * (uGrid - 1.0);
  return texture(uRaw, (g + 0.5) / uGrid).r;
}

float softplus(float x) { return max(x, 0.0) + log(1.0 + exp(-abs(x))); }

void main() {
  float px = gl_FragCoord.x;
  float py = uSize.y - gl_FragCoord.y;  // image rows grow downwards
  vec3 camDir = vec3((px - uLens.z) / uLens.x, -(py - uLens.w) / uLens.y, -1.0);
  vec3 o, d;
  if (uOrtho) {
    o = uEye + uRight * camDir.x + uUp * camDir.y;
    d = -uBack;
  } else {
    o = uEye;
    d = normalize(uRight * camDir.x + uUp * camDir.y + uBack * camDir.z);
  }
  vec3 inv = 1.0 / d;
  vec3 t0 = (uLo - o) * inv, t1 = (uHi - o) * inv;
  vec3 tmin = min(t0, t1), tmax = max(t0, t1);
  float tNear = max(max(max(tmin.x, tmin.y), tmin.z), 0.0);
  float tFar = min(min(tmax.x, tmax.y), tmax.z);
  vec3 rgb = vec3(0.0);
  float opacity = 0.0;
  float depth = 0.0;  // optical depth so far
  vec3 cells = uGrid - 1.0;
  if (tFar > tNear) {
    int count = min(int(ceil((tFar - tNear) / uStep)), ${MAX_STEPS});
    int k = 0;
    while (k < count) {
      float t = tNear + (float(k) + 0.5) * uStep;
      if (t >= tFar) break;
      vec3 p = o + t * d;
      vec3 g = (p - uLo) / (uHi - uLo) * cells;   // in cells
      vec3 cell = clamp(floor(g), vec3(0.0), cells - 1.0);
      vec3 block = floor(cell / ${COARSE_CELLS.toFixed(1)});
      if (texelFetch(uCoarse, ivec3(block), 0).r < 0.5) {
        // jump to the first sample past this clear block
        vec3 blo = uLo + block * ${COARSE_CELLS.toFixed(1)} * (uHi - uLo) / cells;
        vec3 bhi = min(blo + ${COARSE_CELLS.toFixed(1)} * (uHi - uLo) / cells, uHi);
        vec3 a0 = (blo - o) * inv, a1 = (bhi - o) * inv;
        vec3 amax = max(a0, a1);
        float tExit = min(min(amax.x, amax.y), amax.z);
        k = max(k + 1, int(ceil((tExit - tNear) / uStep - 0.5)));
        continue;
      }
      k += 1;
      if (texelFetch(uCells, ivec3(cell), 0).r < 0.5) continue;
      vec3 tc = (g + 0.5) / uGrid;
      float sigma = softplus(texture(uRaw, tc).r) * uScale;
      float tau = sigma * uStep;
      float w = exp(-depth) * (1.0 - exp(-tau));
      depth += tau;
      if (w > 1e-6) {
        float coef[${4 * textures}];
${fetches}
        float b[${basis}];
        ${sh.join("\n        ")}
${level}
        vec3 logit = vec3(0.0);
        for (int j = 0; j < ${basis}; j++) {
          logit += b[j] * vec3(coef[3 * j], coef[3 * j + 1], coef[3 * j + 2]);
        }
        rgb += w / (1.0 + exp(-logit));
        opacity += w;
      }
      if (exp(-depth) < uEps) break;
    }
  }
  outColour = vec4(rgb + uBackground * (1.0 - opacity), 1.0);
}`;
}

function compile(gl, type, source) {
  const shader = gl.createShader(type);
  gl.shaderSource(shader, source);
  gl.compileShader(shader);
  if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
    const log = gl.getShaderInfoLog(shader);
    gl.deleteShader(shader);
    throw new Error(`shader: ${log}`);
  }
  return shader;
}

/** Whether this browser can draw bakes, and why not: {ok, reason}. */
export function webgl2Support(canvas = document.createElement("canvas")) {
  const gl = canvas.getContext("webgl2");
  if (!gl) return { ok: false, reason: "WebGL2 is not available in this browser" };
  return { ok: true, reason: "" };
}

/** One WebGL2 canvas drawing one bake at a time. */
export class BakeRenderer {
  constructor(canvas = document.createElement("canvas")) {
    this.canvas = canvas;
    const gl = canvas.getContext("webgl2", { alpha: false, antialias: false, preserveDrawingBuffer: true });
    if (!gl) throw new Error("WebGL2 is not available in this browser");
    this.gl = gl;
    this.programs = new Map();
    this.textures = [];
    this.bake = null;
    this.bytes = 0;
    this.vao = gl.createVertexArray();
    this.probe = new Uint8Array(4);
  }

  /** Upload a parsed bake (bake.js parseBake); throws naming a GPU limit it passes. */
  load(bake) {
    const gl = this.gl;
    const [nx, ny, nz] = bake.header.grid;
    const limit = gl.getParameter(gl.MAX_3D_TEXTURE_SIZE);
    if (Math.max(nx, ny, nz) > limit) throw new Error(`the bake's grid ${nx}×${ny}×${nz} passes this GPU's 3D texture limit of ${limit}`);
    const dense = denseBake(bake);
    const bytes = textureBytes(dense);
    if (bytes > MAX_TEXTURE_BYTES) throw new Error(`the bake needs ${Math.round(bytes / 2 ** 20)} MB of textures, over ${MAX_TEXTURE_BYTES / 2 ** 20} MB`);
    const layout = {
      textures: dense.coefficients.length, basis: bake.basis, shading: bake.header.shading,
      shDegree: bake.header.sh_degree, powers: bake.header.cosine_powers,
    };
    const program = this.program(layout);
    this.release();
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    const make = (unit, internal, format, type, dims, data, filter) => {
      const tex = gl.createTexture();
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(gl.TEXTURE_3D, tex);
      gl.texParameteri(gl.TEXTURE_3D, gl.TEXTURE_MIN_FILTER, filter);
      gl.texParameteri(gl.TEXTURE_3D, gl.TEXTURE_MAG_FILTER, filter);
      for (const wrap of [gl.TEXTURE_WRAP_S, gl.TEXTURE_WRAP_T, gl.TEXTURE_WRAP_R]) gl.texParameteri(gl.TEXTURE_3D, wrap, gl.CLAMP_TO_EDGE);
      gl.texImage3D(gl.TEXTURE_3D, 0, internal, dims[0], dims[1], dims[2], 0, format, type, data);
      this.textures.push(tex);
    };
    make(0, gl.R16F, gl.RED, gl.HALF_FLOAT, dense.grid, dense.raw, gl.LINEAR);
    make(1, gl.R8, gl.RED, gl.UNSIGNED_BYTE, [nx - 1, ny - 1, nz - 1], dense.cells.map((v) => v * 255), gl.NEAREST);
    make(2, gl.R8, gl.RED, gl.UNSIGNED_BYTE, dense.coarseDims, dense.coarse.map((v) => v * 255), gl.NEAREST);
    dense.coefficients.forEach((data, t) => make(3 + t, gl.RGBA16F, gl.RGBA, gl.FLOAT, dense.grid, data, gl.LINEAR));
    const error = gl.getError();
    if (error !== gl.NO_ERROR) {
      this.release();
      throw new Error(`uploading the bake's textures failed (WebGL error ${error})`);
    }
    gl.useProgram(program);
    const u = (name) => gl.getUniformLocation(program, name);
    gl.uniform1i(u("uRaw"), 0);
    gl.uniform1i(u("uCells"), 1);
    gl.uniform1i(u("uCoarse"), 2);
    for (let t = 0; t < layout.textures; t += 1) gl.uniform1i(u(`uCoef${t}`), 3 + t);
    const h = bake.header;
    gl.uniform3fv(u("uLo"), h.aabb[0]);
    gl.uniform3fv(u("uHi"), h.aabb[1]);
    gl.uniform3fv(u("uGrid"), h.grid);
    gl.uniform3fv(u("uCoarseDims"), dense.coarseDims);
    gl.uniform1f(u("uStep"), h.step);
    gl.uniform1f(u("uScale"), h.density_scale);
    gl.uniform1f(u("uEps"), h.early_stop_eps);
    gl.uniform1f(u("uNormalStep"), h.normal_step ?? 0);
    gl.uniform3fv(u("uBackground"), h.background);
    this.active = program;
    this.bake = bake;
    this.bytes = bytes;
  }

  program(layout) {
    const key = JSON.stringify(layout);
    let program = this.programs.get(key);
    if (program) return program;
    const gl = this.gl;
    program = gl.createProgram();
    gl.attachShader(program, compile(gl, gl.VERTEX_SHADER, VERTEX));
    gl.attachShader(program, compile(gl, gl.FRAGMENT_SHADER, fragmentSource(layout)));
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(`shader link: ${gl.getProgramInfoLog(program)}`);
    this.programs.set(key, program);
    return program;
  }

  /**
   * Draw the loaded bake: camera {azimuth, elevation, distance}, lens {projection, fovDeg,
   * viewHeight}, size in pixels. Returns the milliseconds until the frame was done (a pixel read back).
   */
  draw(camera, lens, width, height) {
    const gl = this.gl;
    if (!this.bake) throw new Error("no bake loaded");
    if (this.canvas.width !== width || this.canvas.height !== height) {
      this.canvas.width = width;
      this.canvas.height = height;
    }
    const started = performance.now();
    const program = this.active;
    gl.useProgram(program);
    const u = (name) => gl.getUniformLocation(program, name);
    const frame = orbitFrame(camera.azimuth, camera.elevation, camera.distance);
    const ortho = lens.projection === "orthographic";
    let fx, fy;
    if (ortho) {
      fx = fy = height / lens.viewHeight;
    } else {
      fx = fy = (0.5 * width) / Math.tan((0.5 * lens.fovDeg * Math.PI) / 180);
    }
    gl.uniform2f(u("uSize"), width, height);
    gl.uniform4f(u("uLens"), fx, fy, 0.5 * width, 0.5 * height);
    gl.uniform1i(u("uOrtho"), ortho ? 1 : 0);
    gl.uniform3fv(u("uRight"), frame.right);
    gl.uniform3fv(u("uUp"), frame.up);
    gl.uniform3fv(u("uBack"), frame.back);
    gl.uniform3fv(u("uEye"), frame.position);
    this.textures.forEach((tex, unit) => {
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(gl.TEXTURE_3D, tex);
    });
    gl.viewport(0, 0, width, height);
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, this.probe); // waits for the frame: an honest time
    return performance.now() - started;
  }

  release() {
    for (const tex of this.textures) this.gl.deleteTexture(tex);
    this.textures = [];
    this.bake = null;
    this.bytes = 0;
  }
}
