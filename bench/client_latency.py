"""Client latency: first frame after page load, and input-to-frame latency while dragging and sliding.

Starts ``visnerf serve`` on a free loopback port (a tiny random checkpoint unless ``--checkpoints``
names a folder of real ones), drives the web client in headless Chromium, and reads the per-frame
figures the client exposes as ``window.__visnerfStats``:

- first frame: navigation start -> first frame drawn (a preview), and -> first full-quality frame;
- drag: a scripted orbit drag at about 60 pointer events per second; for every preview frame drawn,
  the time from the oldest input it answers to the moment it is on the canvas;
- slider sweep: the same for a parameter slider dragged across its range;
- settle: last input -> full-quality frame drawn (includes the client's 150 ms idle wait), and
  -> the full-quality frame at the view's size that follows it on a 1280x860 page.

``--gestures`` drags and as many slider sweeps (each ending elsewhere, so that no settled frame
comes from the server's cache), with ``LOOK_S`` seconds of looking between them, are pooled.

Writes bench/results/client_latency.json and .md (median and p95). Targets (CPU): first frame
within 1 s of page load, previews within 150 ms of input while dragging, the frame at the view's
size within 1.5 s of the last input.

    python bench/client_latency.py [--checkpoints DIR --scene ID] [--loads 5] [--seconds 3]
"""

import visnerf  # noqa: F401  (before torch: it sets the OpenMP wait policy that torch reads once)

# isort: split
import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
from bench_common import cpu_description, write_json

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
CHROMIUM = os.environ.get("VISNERF_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
TARGET_FIRST_FRAME_MS = 1000.0
TARGET_PREVIEW_MS = 150.0
TARGET_SCREEN_MS = 1500.0
VIEWPORT = {"width": 1280, "height": 860}


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(checkpoints: Path, log_path: Path) -> tuple[subprocess.Popen, str]:
    port = free_port()
    cmd = [
        sys.executable, "-m", "visnerf.cli", "serve",
        "--host", "127.0.0.1", "--port", str(port), "--checkpoints", str(checkpoints),
    ]  # fmt: skip
    log = log_path.open("w")
    process = subprocess.Popen(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"server exited with {process.returncode}; see {log_path}")
        try:
            with urllib.request.urlopen(base + "/api/ready", timeout=2) as response:
                if response.status == 200:
                    return process, base
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            pass
        time.sleep(0.2)
    process.terminate()
    raise RuntimeError(f"server not ready after 90 s; see {log_path}")


def summary(values: list[float]) -> dict[str, float | int | None]:
    if not values:
        return {"n": 0, "median": None, "p95": None, "min": None, "max": None}
    a = np.asarray(values, dtype=float)
    return {
        "n": int(a.size),
        "median": round(float(np.median(a)), 1),
        "p95": round(float(np.percentile(a, 95)), 1),
        "min": round(float(a.min()), 1),
        "max": round(float(a.max()), 1),
    }


def wait_settled(page, timeout_ms: float = 30_000) -> None:
    page.wait_for_function("window.__visnerfSettled && window.__visnerfSettled()", timeout=timeout_ms)


def frames_since(page, t0: float) -> list[dict]:
    return page.evaluate("(t0) => window.__visnerfStats.frames.filter(f => f.shownAt >= t0)", t0)


def measure_loads(browser, url: str, loads: int) -> dict:
    first, first_full, dom_loaded = [], [], []
    for i in range(loads):
        context = browser.new_context(viewport=VIEWPORT)
        page = context.new_page()
        # A different azimuth each time, so the server's frame cache never answers for the renderer.
        page.goto(f"{url}&az={-150 + 37 * i}")
        page.wait_for_function("window.__visnerfStats && window.__visnerfStats.firstFullFrameMs !== null")
        stats = page.evaluate(
            """() => ({
                first: __visnerfStats.firstFrameMs,
                full: __visnerfStats.firstFullFrameMs,
                dcl: performance.getEntriesByType('navigation')[0].domContentLoadedEventEnd,
            })"""
        )
        first.append(stats["first"])
        first_full.append(stats["full"])
        dom_loaded.append(stats["dcl"])
        context.close()
    return {
        "first_frame_ms": summary(first),
        "first_full_frame_ms": summary(first_full),
        "dom_content_loaded_ms": summary(dom_loaded),
    }


def scripted_drag(page, seconds: float) -> list[dict]:
    """Orbit: a smooth back-and-forth drag over the view, one pointer event every ~16 ms."""
    wait_settled(page)
    box = page.locator("#viewport").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    t0 = page.evaluate("performance.now()")
    page.mouse.move(cx, cy)
    page.mouse.down()
    steps = int(seconds * 60)
    for i in range(steps):
        phase = 2 * np.pi * i / steps
        page.mouse.move(cx + 150 * np.sin(phase), cy + 60 * np.sin(2 * phase))
        page.wait_for_timeout(16)
    page.mouse.up()
    wait_settled(page)
    return frames_since(page, t0)


def scripted_slider_sweep(page, name: str, seconds: float, end: float) -> list[dict]:
    """Drag a parameter slider's thumb from one end of its track to the other and back to the
    fraction ``end`` of it (a different end each sweep: its frames are not in the server's cache)."""
    wait_settled(page)
    slider = page.locator(f'.param[data-set="A"][data-param="{name}"] input[type=range]')
    box = slider.bounding_box()
    y = box["y"] + box["height"] / 2
    left, right = box["x"] + 7, box["x"] + box["width"] - 7
    value = float(slider.input_value())
    lo, hi = float(slider.get_attribute("min")), float(slider.get_attribute("max"))
    start = left + (right - left) * ((value - lo) / (hi - lo) if hi > lo else 0.5)
    t0 = page.evaluate("performance.now()")
    page.mouse.move(start, y)
    page.mouse.down()
    steps = int(seconds * 60)
    for i in range(steps):
        c = np.cos(2 * np.pi * i / steps)
        u = 0.5 - 0.5 * c if 2 * i < steps else end + (1.0 - end) * (0.5 - 0.5 * c)  # 0 -> 1 -> end
        page.mouse.move(left + (right - left) * u, y)
        page.wait_for_timeout(16)
    page.mouse.up()
    wait_settled(page)
    return frames_since(page, t0)


LOOK_S = 5.0
"""Seconds a user looks at a settled view before the next gesture: a single user keeps within the
server's default rate limit (previews while dragging cost more than it refills)."""


def looked_at(page, frames: list[dict]) -> list[dict]:
    """``frames``, after ``LOOK_S`` seconds of looking at the settled view."""
    page.wait_for_timeout(LOOK_S * 1000)
    return frames


def preview_fps(frames: list[dict]) -> float | None:
    """Previews drawn a second over one gesture (first to last preview)."""
    previews = [f for f in frames if f["channel"] == "A" and f["quality"] == "preview"]
    span_s = (previews[-1]["shownAt"] - previews[0]["shownAt"]) / 1000 if len(previews) > 1 else 0.0
    return (len(previews) - 1) / span_s if span_s > 0 else None


def describe_frames(gestures: list[list[dict]], seconds: float) -> dict:
    """The frames of repeated gestures of ``seconds`` each, pooled (fps: the median gesture's)."""
    frames = [f for g in gestures for f in g]
    previews = [f for f in frames if f["channel"] == "A" and f["quality"] == "preview"]
    fulls = [f for f in frames if f["channel"] == "A" and f["quality"] == "full" and f.get("stage") != "screen"]
    screens = [f for f in frames if f["channel"] == "A" and f.get("stage") == "screen"]
    latency = [f["latencyMs"] for f in previews if f.get("latencyMs") is not None]
    dropped = [f.get("dropped") or 0 for f in frames if f["channel"] == "A"]
    fps = [r for r in (preview_fps(g) for g in gestures) if r is not None]
    return {
        "input_seconds": seconds,
        "gestures": len(gestures),
        "preview_frames": len(previews),
        "preview_fps": round(float(np.median(fps)), 1) if fps else None,
        "preview_latency_ms": summary(latency),
        "preview_render_ms": summary([f["renderMs"] for f in previews if f.get("renderMs") is not None]),
        "preview_size": sorted({f"{f['width']}x{f['height']}" for f in previews}),
        # The frame header's `dropped` counts the stale requests the server skipped on this socket.
        "dropped_by_server": int(max(dropped) - min(dropped)) if dropped else 0,
        "full_frames": len(fulls),
        "full_settle_ms": summary([f["settleMs"] for f in fulls if f.get("settleMs") is not None]),
        "full_render_ms": summary([f["renderMs"] for f in fulls if f.get("renderMs") is not None]),
        "full_size": sorted({f"{f['width']}x{f['height']}" for f in fulls}),
        "screen_frames": len(screens),
        "screen_settle_ms": summary([f["settleMs"] for f in screens if f.get("settleMs") is not None]),
        "screen_render_ms": summary([f["renderMs"] for f in screens if f.get("renderMs") is not None]),
        "screen_size": sorted({f"{f['width']}x{f['height']}" for f in screens}),
    }


def write_markdown(result: dict, path: Path) -> None:
    def row(label: str, s: dict, target: float | None = None) -> str:
        ok = "" if target is None or s["p95"] is None else (" yes" if s["median"] <= target else " **no**")
        med = "–" if s["median"] is None else f"{s['median']:.0f}"
        p95 = "–" if s["p95"] is None else f"{s['p95']:.0f}"
        tgt = "" if target is None else f"≤ {target:.0f} (median){ok}"
        return f"| {label} | {med} | {p95} | {s['n']} | {tgt} |"

    loads, drag, slider = result["page_load"], result["drag"], result["slider"]
    lines = [
        "# Client latency",
        "",
        f"Recorded {result['recorded']} by `bench/client_latency.py` on {result['machine']['cpu']} "
        f"({result['machine']['cpus']} CPUs, shared; load average {result['machine']['load_avg_before']} "
        "before the run), "
        f"headless Chromium {result['browser_version']}, server {result['server_version']} on CPU, "
        f"scene `{result['scene']}` ({result['scene_note']}), full frames {result['full_size']}.",
        "",
        "| measure | median ms | p95 ms | n | target |",
        "| --- | ---: | ---: | ---: | --- |",
        row("page load → first frame (preview)", loads["first_frame_ms"], TARGET_FIRST_FRAME_MS),
        row("page load → first full-quality frame", loads["first_full_frame_ms"]),
        row("drag: input → preview on screen", drag["preview_latency_ms"], TARGET_PREVIEW_MS),
        row("drag: last input → full frame", drag["full_settle_ms"]),
        row(f"drag: last input → frame at the view's size ({', '.join(drag['screen_size'])})",
            drag["screen_settle_ms"], TARGET_SCREEN_MS),
        row("slider: input → preview on screen", slider["preview_latency_ms"], TARGET_PREVIEW_MS),
        row("slider: last input → full frame", slider["full_settle_ms"]),
        row("slider: last input → frame at the view's size", slider["screen_settle_ms"], TARGET_SCREEN_MS),
        "",
        f"Drag: {drag['preview_frames']} previews in {drag['gestures']} drags of {drag['input_seconds']} s "
        f"({drag['preview_fps']} fps, the median drag's; {', '.join(drag['preview_size'])}, server render median "
        f"{drag['preview_render_ms']['median']} ms). Slider: {slider['preview_frames']} previews "
        f"({slider['preview_fps']} fps, render median {slider['preview_render_ms']['median']} ms). "
        f"Full frames render in {drag['full_render_ms']['median']} ms (median), frames at the view's size in "
        f"{drag['screen_render_ms']['median']} ms (the server's render and encoding).",
        "",
        "Each page load opens a different azimuth (a fresh browser context, nothing cached), so every "
        "first frame is really rendered. The first frame is a low-resolution preview sent ahead of the "
        "full-quality one.",
        "",
        "Latency is measured in the page: from the browser's timestamp of the oldest input event a frame "
        "answers to the moment the frame is drawn on the canvas (`window.__visnerfStats`). The settle time "
        "includes the client's 150 ms idle wait before it asks for the full-quality PNG.",
        "",
    ]
    path.write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--checkpoints", type=Path, help="folder of .safetensors (default: a tiny one)")
    parser.add_argument("--scene", help="scene id (default: the first the server lists)")
    parser.add_argument("--param", help="parameter to sweep (default: the scene's first)")
    parser.add_argument("--loads", type=int, default=5, help="page loads for the first-frame figure")
    parser.add_argument("--seconds", type=float, default=3.0, help="length of each scripted input")
    parser.add_argument("--gestures", type=int, default=5,
                        help="drags and slider sweeps, each, whose settled frames are pooled (default 5)")
    parser.add_argument("--out", type=Path, default=RESULTS / "client_latency.json")
    args = parser.parse_args(argv)

    from playwright.sync_api import sync_playwright

    RESULTS.mkdir(parents=True, exist_ok=True)
    load_before = [round(x, 2) for x in os.getloadavg()]
    with tempfile.TemporaryDirectory(prefix="visnerf-bench-") as tmp:
        checkpoints = args.checkpoints
        note = "checkpoints from " + str(args.checkpoints)
        if checkpoints is None:
            from visnerf.testing import make_tiny_checkpoint

            checkpoints = Path(tmp)
            axes = [("time", [0.0, 0.5, 1.0]), ("isovalue", [0.2, 0.8])]
            make_tiny_checkpoint(checkpoints / "tiny.safetensors", param_axes=axes, kind="dvr", title="Tiny")
            note = "tiny random checkpoint, 64x64 training images, K=2"
        process, base = start_server(checkpoints, Path(tmp) / "server.log")
        try:
            with urllib.request.urlopen(base + "/api/scenes") as r:
                scenes = json.loads(r.read())
            with urllib.request.urlopen(base + "/api/health") as r:
                health = json.loads(r.read())
            scene = next(s for s in scenes if s["id"] == args.scene) if args.scene else scenes[0]
            param = args.param or (scene["params"][0]["name"] if scene["params"] else None)
            url = f"{base}/?scene={scene['id']}"
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                loads = measure_loads(browser, url, args.loads)
                context = browser.new_context(viewport=VIEWPORT)
                page = context.new_page()
                page.goto(url)
                wait_settled(page)
                full_size = page.inner_text("#stat-size")
                drag = describe_frames([looked_at(page, scripted_drag(page, args.seconds))
                                        for _ in range(args.gestures)], args.seconds)
                slider = (describe_frames([looked_at(page, scripted_slider_sweep(page, param, args.seconds, end))
                                           for end in np.linspace(0.15, 0.85, args.gestures)], args.seconds)
                          if param else {})
                version = browser.version
                browser.close()
        finally:
            process.terminate()
            process.wait(timeout=10)

    slider_median = slider.get("preview_latency_ms", {}).get("median")
    result = {
        "recorded": time.strftime("%Y-%m-%d %H:%M:%S"),
        "machine": {
            "cpu": cpu_description(),
            "cpus": os.cpu_count(),
            "load_avg_before": load_before,
        },
        "browser_version": version,
        "server_version": health.get("version"),
        "scene": scene["id"],
        "scene_note": note,
        "swept_param": param,
        "full_size": full_size,
        "page_load": loads,
        "drag": drag,
        "slider": slider,
        "targets": {"first_frame_ms": TARGET_FIRST_FRAME_MS, "preview_latency_ms": TARGET_PREVIEW_MS},
        "meets_targets": {
            "first_frame": loads["first_frame_ms"]["median"] <= TARGET_FIRST_FRAME_MS,
            "drag_preview": (drag["preview_latency_ms"]["median"] or 1e9) <= TARGET_PREVIEW_MS,
            "slider_preview": (slider_median or 1e9) <= TARGET_PREVIEW_MS,
            "drag_screen": (drag["screen_settle_ms"]["median"] or 1e9) <= TARGET_SCREEN_MS,
            "slider_screen": (slider.get("screen_settle_ms", {}).get("median") or 1e9) <= TARGET_SCREEN_MS,
        },
    }
    write_json(args.out, result)
    write_markdown(result, args.out.with_suffix(".md"))
    print(json.dumps({k: result[k] for k in ("page_load", "meets_targets")}, indent=2))
    print(f"wrote {args.out} and {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
