"""The browser's local frames: draw time at 1280x720 in headless Chromium's software WebGL2
(SwiftShader, on this machine's CPU cores), each bundled scene's texture memory, and the work of
a frame counted on the CPU (texture fetches a pixel, as the shader makes them), from which the
frame rate on a laptop GPU is estimated.

    .venv/bin/python bench/local_frames.py

Writes bench/results/local_frames.{json,md}. The estimate divides a laptop GPU's filtered
texture rate (LAPTOP_TEXELS_PER_S) by the frame's fetches; it says what the frame asks of a GPU,
not what a given one does.
"""

import visnerf  # noqa: F401  (before torch: the OpenMP wait policy)

# isort: split
import argparse
import functools
import http.server
import math
import statistics
import sys
import tempfile
import threading
from pathlib import Path

import torch
from bench_common import RESULTS, ROOT, load_average, machine_record, markdown_header, write_results

from visnerf.bake.bake_file import bake_bytes
from visnerf.bake.bake_render import DenseBake
from visnerf.bake.scene_bake import bake_scene
from visnerf.data.cameras import Intrinsics, image_rays, orbit_c2w
from visnerf.inference import load_scene
from visnerf.rendering.aabb import intersect_aabb_torch

WIDTH, HEIGHT = 1280, 720
LAPTOP_TEXELS_PER_S = 50e9
"""Filtered texture fetches a second of a laptop's integrated GPU (tens of GTexel/s; Intel Iris
Xe about 50): the estimate assumes the shader is bound by its fetches."""
COARSE = 8
PAGE = """<!doctype html><script type="module">
import { parseBake } from "/client/js/bake.js";
import { BakeRenderer } from "/client/js/bake_renderer.js";
window.run = async (name, cam, frames) => {
  const bake = parseBake(await (await fetch(`/bakes/${name}.bake`)).arrayBuffer());
  const r = new BakeRenderer();
  r.load(bake);
  const ms = [];
  for (let i = 0; i < frames; i += 1) {
    ms.push(r.draw({azimuth: 30 + 10 * i, elevation: 20, distance: cam.distance},
                   {projection: "perspective", fovDeg: cam.fov_deg}, WIDTH, HEIGHT));
  }
  return {ms, bytes: r.bytes};
};
window.ready = true;
</script>""".replace("WIDTH", str(WIDTH)).replace("HEIGHT", str(HEIGHT))


def fetches_a_pixel(dense: DenseBake, c2w: torch.Tensor, intrinsics: Intrinsics) -> dict:
    """Texture fetches of one frame as the shader makes them, counted per pixel: the coarse grid
    at each sample in an occupied block and once a clear block, the cell grid and the raw density
    at each sample in an occupied block, the coefficient textures (and four probes for ``level``)
    at each sample that weighs; until the transmittance is under the bake's epsilon."""
    h = dense.bake.header
    textures = math.ceil(h.channels / 4)
    rays_o, rays_d = image_rays(c2w.float(), intrinsics)
    o, d = rays_o.reshape(-1, 3), rays_d.reshape(-1, 3)
    t_near, t_far, hit = intersect_aabb_torch(o, d, torch.tensor(h.aabb, dtype=torch.float32))
    cells = torch.tensor(h.cells, dtype=torch.float32)
    coarse_occ = torch.nn.functional.max_pool3d(dense.occupancy[None, None].float(), COARSE, COARSE, ceil_mode=True)[0, 0] > 0
    total = torch.zeros(o.shape[0])
    for start in range(0, o.shape[0], 4096):
        sl = slice(start, start + 4096)
        hit_s = hit[sl]
        if not hit_s.any():
            continue
        tn, tf = t_near[sl], t_far[sl]
        count = int(math.ceil(float((tf - tn)[hit_s].max()) / h.step))
        t = tn[:, None] + (torch.arange(count)[None] + 0.5) * h.step
        valid = (t < tf[:, None]) & hit_s[:, None]
        p = o[sl, None] + t[..., None] * d[sl, None]
        unit = dense.to_unit(p.reshape(-1, 3))
        g = (unit + 1) * 0.5 * cells
        cell = torch.minimum(g.floor().clamp_min(0), cells - 1).long()
        block = cell // COARSE
        in_block = coarse_occ[block[:, 2], block[:, 1], block[:, 0]].view(valid.shape) & valid
        occupied = dense.occupancy[cell[:, 2], cell[:, 1], cell[:, 0]].view(valid.shape) & in_block
        raw = dense.sample(dense.raw, unit)[:, 0].view(valid.shape)
        sigma = torch.where(occupied, torch.nn.functional.softplus(raw) * h.density_scale, 0.0)
        depth = torch.cumsum(sigma * h.step, dim=1)
        before = torch.cat([torch.zeros_like(depth[:, :1]), depth[:, :-1]], dim=1)
        alive = torch.exp(-before) >= h.early_stop_eps  # the shader stops after the sample that crosses
        weight = torch.exp(-before) * -torch.expm1(-sigma * h.step)
        shaded = (weight > 1e-6) & occupied & alive
        key = (block[:, 0] * 4096 + block[:, 1]) * 4096 + block[:, 2]
        key = key.view(valid.shape)
        clear = valid & ~in_block & alive
        new_block = clear & torch.cat([torch.ones_like(clear[:, :1]), key[:, 1:] != key[:, :-1]], dim=1)
        per_ray = (2 * (in_block & alive)).sum(1) + occupied.logical_and(alive).sum(1) + new_block.sum(1)
        per_ray = per_ray + shaded.sum(1) * (textures + (4 if h.shading == "level" else 0))
        total[sl] = per_ray.float()
    return {"mean": float(total.mean()), "p95": float(total.quantile(0.95))}


def browser_times(bakes: dict[str, Path], cameras: dict[str, dict], frames: int) -> dict[str, dict]:
    from playwright.sync_api import sync_playwright

    site = Path(tempfile.mkdtemp())
    (site / "index.html").write_text(PAGE)
    (site / "client").symlink_to(ROOT / "client")
    (site / "bakes").mkdir()
    for name, path in bakes.items():
        (site / "bakes" / f"{name}.bake").symlink_to(path)

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(site)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    out = {}
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=["--no-sandbox", "--disable-gpu"])
            page = browser.new_page()
            page.goto(f"http://127.0.0.1:{server.server_address[1]}/index.html")
            page.wait_for_function("window.ready")
            for name in bakes:
                r = page.evaluate("([n, c, f]) => run(n, c, f)", [name, cameras[name], frames])
                out[name] = {"draw_ms_median": statistics.median(r["ms"][1:]), "first_ms": r["ms"][0],
                             "texture_mb": r["bytes"] / 1e6}
                print(name, out[name], file=sys.stderr, flush=True)
            browser.close()
    finally:
        server.shutdown()
    return out


def write_markdown(path: Path, record: dict) -> None:
    lines = markdown_header("Local frames: the browser's renderer", record)
    lines += ["", f"{WIDTH}x{HEIGHT} frames of each bundled scene's default bake, {record['frames']} draws a scene "
              "(the first, which compiles the shader, left out of the median), in headless Chromium's software "
              "WebGL2 (SwiftShader on this CPU). Fetches: texture reads a pixel counted on the CPU along the "
              f"shader's samples; the laptop estimate is {LAPTOP_TEXELS_PER_S / 1e9:.0f} GTexel/s over the frame's "
              "fetches.", "",
              "| scene | shading | bake MB (gzip on the wire) | textures MB | draw ms (software, median) | "
              "fetches a pixel (mean / p95) | laptop GPU estimate, frames a second |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, r in record["scenes"].items():
        lines.append(f"| {name} | {r['shading']} | {r['bake_mb']:.2f} ({r['wire_mb']:.2f}) | {r['texture_mb']:.1f} | "
                     f"{r['draw_ms_median']:.0f} | {r['fetches']['mean']:.0f} / {r['fetches']['p95']:.0f} | "
                     f"{r['laptop_fps']:.0f} |")
    path.write_text("\n".join(lines) + "\n")


def main() -> int:
    import gzip

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=4)
    args = ap.parse_args()
    record = {**machine_record(), "command": " ".join(["bench/local_frames.py", *sys.argv[1:]]), "frames": args.frames,
              "load_average_1min": {"before": load_average()}, "scenes": {}}
    folder = Path(tempfile.mkdtemp())
    bakes, cameras = {}, {}
    for path in sorted((ROOT / "checkpoints").glob("*.safetensors")):
        scene = load_scene(path)
        bake = bake_scene(scene)
        data = bake_bytes(bake)
        bakes[path.stem] = folder / f"{path.stem}.bake"
        bakes[path.stem].write_bytes(data)
        cam = scene.info.camera
        cameras[path.stem] = {"distance": cam["distance"], "fov_deg": cam["fov_deg"]}
        dense = DenseBake.of(bake)
        c2w = torch.tensor(orbit_c2w(30.0, 20.0, cam["distance"]), dtype=torch.float32)
        fetches = fetches_a_pixel(dense, c2w, Intrinsics.from_fov(WIDTH, HEIGHT, math.radians(cam["fov_deg"])))
        record["scenes"][path.stem] = {"shading": bake.header.shading, "bake_mb": len(data) / 1e6,
                                       "wire_mb": len(gzip.compress(data, 1)) / 1e6, "fetches": fetches,
                                       "laptop_fps": LAPTOP_TEXELS_PER_S / (fetches["mean"] * WIDTH * HEIGHT)}
    for name, times in browser_times(bakes, cameras, args.frames).items():
        record["scenes"][name].update(times)
    record["load_average_1min"]["after"] = load_average()
    write_results(RESULTS, "local_frames", record, write_markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
