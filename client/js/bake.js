// Bakes (docs/bake_format.md): parse the file, check it, and lay its bricks out as the dense
// arrays the renderer uploads as 3D textures. No DOM and no WebGL here (node tests it).

export const BAKE_FORMAT = "visnerf-bake";
export const BAKE_VERSION = 1;
const DTYPES = { F16: [Uint16Array, 2], F32: [Float32Array, 4], U8: [Uint8Array, 1], I16: [Int16Array, 2] };
const ARRAYS = { bricks: "I16", raw: "F16", codes: "U8", low: "F32", scale: "F32", occupancy: "U8" };
/** Raw density of the vertices no brick stores (float16 bits of -100): no density. */
export const FILL_HALF = 0xd640;
/** Cells a side of a block of the coarse occupancy grid the renderer skips empty space with. */
export const COARSE_CELLS = 8;

export class BakeError extends Error {}

/** Header and typed arrays of a bake; BakeError names the first problem. */
export function parseBake(buffer) {
  if (!(buffer instanceof ArrayBuffer) || buffer.byteLength < 8) throw new BakeError("a bake starts with an 8-byte header length");
  const view = new DataView(buffer);
  const n = Number(view.getBigUint64(0, true));
  if (n < 2 || n > 1 << 20 || 8 + n > buffer.byteLength) throw new BakeError(`header length ${n} does not fit the file's ${buffer.byteLength} bytes`);
  let entries;
  try {
    entries = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 8, n)));
  } catch (err) {
    throw new BakeError(`the header is not JSON: ${err.message}`);
  }
  let header;
  try {
    header = JSON.parse(entries.__metadata__.bake);
  } catch {
    throw new BakeError("the header has no bake entry");
  }
  if (header.format !== BAKE_FORMAT) throw new BakeError(`not a bake file (format ${JSON.stringify(header.format)})`);
  if (header.version !== BAKE_VERSION) throw new BakeError(`bake version ${header.version} is not supported (this reads ${BAKE_VERSION})`);
  const body = 8 + n;
  const arrays = {};
  for (const [name, dtype] of Object.entries(ARRAYS)) {
    const entry = entries[name];
    if (!entry || entry.dtype !== dtype) throw new BakeError(`array ${name} must be ${dtype}`);
    const [Type, size] = DTYPES[dtype];
    const [begin, end] = entry.data_offsets;
    const count = entry.shape.reduce((a, b) => a * b, 1);
    if (!(begin >= 0 && end >= begin && body + end <= buffer.byteLength && end - begin === count * size)) {
      throw new BakeError(`array ${name}: bytes ${begin}..${end} do not hold its shape ${JSON.stringify(entry.shape)}`);
    }
    arrays[name] = new Type(buffer.slice(body + begin, body + end)); // a copy: aligned for its type
    arrays[name].shape = entry.shape;
  }
  const basis = (header.sh_degree + 1) ** 2 + (header.shading === "level" ? 1 + header.cosine_powers.length : 0);
  const channels = 3 * basis;
  const b = header.brick;
  const bricks = arrays.bricks.shape[0];
  const want = { raw: [bricks, b, b, b], codes: [bricks, b, b, b, channels], low: [bricks, channels], scale: [bricks, channels] };
  for (const [name, shape] of Object.entries(want)) {
    if (JSON.stringify(arrays[name].shape) !== JSON.stringify(shape)) throw new BakeError(`array ${name} must have shape ${JSON.stringify(shape)}`);
  }
  return { header, arrays, basis, channels, bricks };
}

/**
 * The bake over its whole grid, x fastest (a 3D texture's layout): `raw` float16 bits per vertex,
 * `coefficients` one Float32Array of 4 channels a vertex per texture (ceil(C / 4) of them), `cells`
 * a byte a cell (1: sampled), `coarse` a byte a block of COARSE_CELLS^3 cells (1: some cell sampled).
 */
export function denseBake(bake) {
  const { header, arrays, channels } = bake;
  const [nx, ny, nz] = header.grid;
  const b = header.brick;
  const vertices = nx * ny * nz;
  const raw = new Uint16Array(vertices).fill(FILL_HALF);
  const textures = Math.ceil(channels / 4);
  const coefficients = Array.from({ length: textures }, () => new Float32Array(vertices * 4));
  const { bricks, raw: rawBricks, codes, low, scale } = arrays;
  for (let i = 0; i < bake.bricks; i += 1) {
    const bx = bricks[3 * i] * b, by = bricks[3 * i + 1] * b, bz = bricks[3 * i + 2] * b;
    for (let k = 0; k < b && bz + k < nz; k += 1) {
      for (let j = 0; j < b && by + j < ny; j += 1) {
        for (let l = 0; l < b && bx + l < nx; l += 1) {
          const v = ((bz + k) * ny + (by + j)) * nx + (bx + l);
          const local = (k * b + j) * b + l;
          raw[v] = rawBricks[i * b * b * b + local];
          const codeBase = (i * b * b * b + local) * channels;
          for (let c = 0; c < channels; c += 1) {
            const value = low[i * channels + c] + codes[codeBase + c] * scale[i * channels + c];
            coefficients[c >> 2][v * 4 + (c & 3)] = value;
          }
        }
      }
    }
  }
  const [cx, cy, cz] = [nx - 1, ny - 1, nz - 1];
  const cells = new Uint8Array(cx * cy * cz);
  const bits = arrays.occupancy;
  for (let i = 0; i < cells.length; i += 1) cells[i] = (bits[i >> 3] >> (i & 7)) & 1;
  const coarseDims = [cx, cy, cz].map((c) => Math.ceil(c / COARSE_CELLS));
  const coarse = new Uint8Array(coarseDims[0] * coarseDims[1] * coarseDims[2]);
  for (let z = 0; z < cz; z += 1) {
    for (let y = 0; y < cy; y += 1) {
      for (let x = 0; x < cx; x += 1) {
        if (cells[(z * cy + y) * cx + x]) {
          const g = ((z >> 3) * coarseDims[1] + (y >> 3)) * coarseDims[0] + (x >> 3);
          coarse[g] = 1;
        }
      }
    }
  }
  return { raw, coefficients, cells, coarse, coarseDims, grid: [nx, ny, nz] };
}

/** GPU memory the dense textures take, bytes. */
export function textureBytes(dense) {
  const vertices = dense.raw.length;
  return vertices * 2 + dense.coefficients.length * vertices * 8 + dense.cells.length + dense.coarse.length;
}

/** Camera-to-world rotation and position of an orbit camera (visnerf.data.cameras.orbit_c2w):
 * {right, up, back, position}, each [x, y, z]. */
export function orbitFrame(azimuthDeg, elevationDeg, distance) {
  const az = (azimuthDeg * Math.PI) / 180;
  const el = (elevationDeg * Math.PI) / 180;
  const back = [Math.cos(el) * Math.sin(az), Math.sin(el), Math.cos(el) * Math.cos(az)];
  const right = [Math.cos(az), 0, -Math.sin(az)];
  const up = [
    back[1] * right[2] - back[2] * right[1],
    back[2] * right[0] - back[0] * right[2],
    back[0] * right[1] - back[1] * right[0],
  ];
  return { right, up, back, position: back.map((v) => v * distance) };
}
