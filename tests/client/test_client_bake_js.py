"""client/js/bake.js against the Python reader: the same file gives the same dense arrays, the
orbit frame equals ``orbit_c2w``, and a broken file is refused."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from visnerf.bake.bake_file import bake_bytes
from visnerf.data.cameras import orbit_c2w

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests" / "model" / "bake"))
from test_bake_file import small_bake  # noqa: E402

SCRIPT = """
import { readFileSync } from "node:fs";
import { parseBake, denseBake, orbitFrame, BakeError } from "%s";
const data = readFileSync(process.argv[2]);
const buffer = data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength);
const dense = denseBake(parseBake(buffer));
let refused = "";
try { parseBake(buffer.slice(0, 100)); } catch (err) { refused = (err instanceof BakeError) + " " + err.message; }
console.log(JSON.stringify({
  raw: Array.from(dense.raw), coefficients: dense.coefficients.map((c) => Array.from(c)),
  cells: Array.from(dense.cells), coarse: Array.from(dense.coarse), coarseDims: dense.coarseDims,
  frame: orbitFrame(37, -61, 2.5), refused,
}));
"""


@pytest.mark.parametrize("shading", ["sh", "level"])
def test_the_browser_reads_a_bake_as_python_does(tmp_path, shading) -> None:
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    bake = small_bake(shading)
    path = tmp_path / "b.bake"
    path.write_bytes(bake_bytes(bake))
    script = tmp_path / "read.mjs"
    script.write_text(SCRIPT % (REPO / "client" / "js" / "bake.js").as_uri())
    out = subprocess.run([node, str(script), str(path)], capture_output=True, text=True, timeout=60, check=True)
    got = json.loads(out.stdout)
    raw = np.array(got["raw"], dtype=np.uint16).view(np.float16).astype(np.float32).reshape(bake.dense_raw().shape)
    assert np.array_equal(raw, bake.dense_raw())
    coef = np.stack([np.array(c, dtype=np.float32).reshape(*raw.shape, 4) for c in got["coefficients"]], -2)
    coef = coef.reshape(*raw.shape, -1)[..., : bake.header.channels]
    assert np.allclose(coef, bake.dense_coefficients(), rtol=1e-6, atol=1e-6)
    cells = np.array(got["cells"]).reshape(bake.dense_occupancy().shape).astype(bool)
    assert np.array_equal(cells, bake.dense_occupancy())
    cz, cy, cx = cells.shape
    coarse = np.array(got["coarse"]).reshape(got["coarseDims"][2], got["coarseDims"][1], got["coarseDims"][0])
    for z, y, x in np.argwhere(cells):
        assert coarse[z // 8, y // 8, x // 8] == 1
    assert coarse.sum() == len({(z // 8, y // 8, x // 8) for z, y, x in np.argwhere(cells)})
    c2w = orbit_c2w(37.0, -61.0, 2.5)
    frame = got["frame"]
    for name, column in (("right", 0), ("up", 1), ("back", 2), ("position", 3)):
        assert np.allclose(frame[name], c2w[:3, column], atol=1e-12), name
    assert got["refused"].startswith("true ")
