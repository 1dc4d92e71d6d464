"""Load test of the render server: N concurrent HTTP clients on loopback for a bounded time.

Starts ``visnerf serve`` itself (a subprocess on a free loopback port), waits until it is ready,
then runs ``--clients`` threads, each with its own ``httpx.Client``, requesting frames from random
viewpoints and parameter values (so the frame cache rarely answers) until ``--duration`` seconds
have passed. Meanwhile it samples the server's resident memory (VmRSS in /proc/PID/status).

Records requests per second, latency percentiles, errors, 503 answers and RSS over time (first
10 s against last 10 s, to show whether memory stays flat) to bench/results/server_load.json and
.md, then stops the server with SIGTERM.

    python bench/server_load.py --tiny --clients 4 --duration 20
    python bench/server_load.py --checkpoints checkpoints/ --clients 8 --duration 30
"""

import argparse
import json
import os
import platform
import random
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import httpx
from bench_common import write_json

ROOT = Path(__file__).resolve().parents[1]
RSS_WINDOW_S = 10.0


@dataclass
class Sample:
    started: float
    """Seconds since the load started."""
    latency_ms: float
    status: int
    """HTTP status, or 0 for a transport error."""


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def read_rss_kb(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (OSError, ValueError):
        return None
    return None


def make_tiny_checkpoints(folder: Path) -> None:
    from visnerf.testing import make_tiny_checkpoint

    make_tiny_checkpoint(folder / "tiny.safetensors")
    make_tiny_checkpoint(
        folder / "tiny2.safetensors",
        [("t", [0.0, 1.0, 2.0]), ("iso", [0.1, 0.3, 0.5])],
        kind="ir",
        title="Tiny 2",
    )


def start_server(checkpoints: Path, port: int, log_path: Path) -> subprocess.Popen:
    with log_path.open("wb") as log:
        return subprocess.Popen(
            [
                sys.executable,
                "-m",
                "visnerf.cli",
                "serve",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
                "--checkpoints",
                str(checkpoints),
                "--no-client",
                "--log-level",
                "warning",
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            env={**os.environ, "VISNERF_TOKEN": "bench-not-used"},
        )


def wait_ready(proc: subprocess.Popen, url: str, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited with status {proc.returncode} before it was ready")
        try:
            if httpx.get(f"{url}/api/ready", timeout=2).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise RuntimeError("server did not become ready in time")


def client_loop(
    url: str,
    scenes: list[dict],
    args: argparse.Namespace,
    t0: float,
    deadline: float,
    seed: int,
    out: list[Sample],
) -> None:
    rng = random.Random(seed)
    with httpx.Client(base_url=url, timeout=max(60.0, args.duration)) as http:
        while time.perf_counter() < deadline:
            scene = rng.choice(scenes)
            query: dict[str, object] = {
                "azimuth": round(rng.uniform(-180, 180), 3),
                "elevation": round(rng.uniform(-60, 60), 3),
                "width": args.width,
                "height": args.height,
                "quality": args.quality,
                "format": args.format,
            }
            for axis in scene["params"]:
                query[axis["name"]] = round(rng.uniform(axis["min"], axis["max"]), 4)
            start = time.perf_counter()
            try:
                response = http.get(f"/api/scenes/{scene['id']}/render", params=query)
                response.read()
                status = response.status_code
            except httpx.HTTPError:
                status = 0
            out.append(Sample(start - t0, (time.perf_counter() - start) * 1e3, status))


def percentile(sorted_values: list[float], q: float) -> float:
    if not sorted_values:
        return float("nan")
    index = min(len(sorted_values) - 1, max(0, round(q / 100 * (len(sorted_values) - 1))))
    return sorted_values[index]


def summarise(samples: list[Sample], rss: list[tuple[float, int]], duration: float) -> dict:
    ok = sorted(s.latency_ms for s in samples if s.status == 200)
    statuses: dict[str, int] = {}
    for s in samples:
        statuses[str(s.status)] = statuses.get(str(s.status), 0) + 1
    first = [kb for t, kb in rss if t <= RSS_WINDOW_S]
    last = [kb for t, kb in rss if t >= duration - RSS_WINDOW_S]

    def mb(values: list[int], fn) -> float | None:  # noqa: ANN001
        return round(fn(values) / 1024, 1) if values else None

    return {
        "requests": len(samples),
        "ok": len(ok),
        "requests_per_s": round(len(ok) / duration, 2),
        "latency_ms": {
            "p50": round(percentile(ok, 50), 2),
            "p95": round(percentile(ok, 95), 2),
            "p99": round(percentile(ok, 99), 2),
            "mean": round(statistics.fmean(ok), 2) if ok else None,
            "max": round(ok[-1], 2) if ok else None,
        },
        "errors": sum(1 for s in samples if s.status != 200 and s.status != 503),
        "status_503": statuses.get("503", 0),
        "status_counts": statuses,
        "rss_mb": {
            "peak": mb([kb for _, kb in rss], max),
            "first_10s_mean": mb(first, statistics.fmean),
            "first_10s_max": mb(first, max),
            "last_10s_mean": mb(last, statistics.fmean),
            "last_10s_max": mb(last, max),
            "samples": len(rss),
        },
    }


def write_markdown(path: Path, result: dict) -> None:
    c, r = result["config"], result["results"]
    lat, rss = r["latency_ms"], r["rss_mb"]
    lines = [
        "# Render server load test",
        "",
        f"`python bench/server_load.py {' '.join(result['argv'])}` on {result['machine']['summary']}, "
        f"{result['date']}.",
        "",
        f"- {c['clients']} concurrent HTTP clients (threads, httpx) on loopback for {c['duration_s']} s; "
        f"`GET /api/scenes/{{id}}/render` at {c['width']}x{c['height']}, quality {c['quality']}, "
        f"format {c['format']}, random viewpoint and parameter values per request.",
        f"- Scenes: {', '.join(result['scenes'])} ({result['checkpoints_note']}).",
        f"- Server: 1 render worker, queue of 8 (defaults); "
        f"exit status after SIGTERM: {result['server_exit_code']}.",
        "",
        "| measure | value |",
        "| --- | --- |",
        f"| frames per second | {r['requests_per_s']} |",
        f"| requests (200) | {r['ok']} of {r['requests']} |",
        f"| latency p50 / p95 / p99 (ms) | {lat['p50']} / {lat['p95']} / {lat['p99']} |",
        f"| latency mean / max (ms) | {lat['mean']} / {lat['max']} |",
        f"| errors (not 200, not 503) | {r['errors']} |",
        f"| 503 (queue full) | {r['status_503']} |",
        f"| server RSS peak (MB) | {rss['peak']} |",
        f"| server RSS first 10 s mean / max (MB) | {rss['first_10s_mean']} / {rss['first_10s_max']} |",
        f"| server RSS last 10 s mean / max (MB) | {rss['last_10s_mean']} / {rss['last_10s_max']} |",
        "",
    ]
    if result.get("notes"):
        lines += ["Notes:", ""] + [f"- {n}" for n in result["notes"]] + [""]
    path.write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--duration", type=float, default=30.0, help="seconds of load")
    parser.add_argument("--checkpoints", type=Path, default=ROOT / "checkpoints")
    parser.add_argument("--tiny", action="store_true", help="serve tiny random checkpoints made for the run")
    parser.add_argument("--width", type=int, default=128)
    parser.add_argument("--height", type=int, default=128)
    parser.add_argument("--quality", choices=["preview", "full"], default="full")
    parser.add_argument("--format", choices=["png", "jpeg", "webp"], default="jpeg")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "server_load")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    with tempfile.TemporaryDirectory(prefix="visnerf-load-") as tmp:
        tmp_dir = Path(tmp)
        if args.tiny:
            checkpoints = tmp_dir / "checkpoints"
            checkpoints.mkdir()
            make_tiny_checkpoints(checkpoints)
            note = "tiny random checkpoints from visnerf.testing.make_tiny_checkpoint, 8^3 grids"
        else:
            checkpoints = args.checkpoints
            if not any(checkpoints.glob("*.safetensors")):
                print(f"no checkpoints in {checkpoints}; use --tiny or --checkpoints DIR", file=sys.stderr)
                return 2
            note = f"checkpoints from {checkpoints}"
        port = free_port()
        url = f"http://127.0.0.1:{port}"
        load_before = os.getloadavg()
        proc = start_server(checkpoints, port, tmp_dir / "server.log")
        try:
            wait_ready(proc, url)
            scenes = httpx.get(f"{url}/api/scenes").json()
            samples: list[Sample] = []
            rss: list[tuple[float, int]] = []
            t0 = time.perf_counter()
            deadline = t0 + args.duration
            stop = threading.Event()

            def sample_rss() -> None:
                while not stop.is_set():
                    kb = read_rss_kb(proc.pid)
                    if kb is not None:
                        rss.append((time.perf_counter() - t0, kb))
                    stop.wait(0.25)

            sampler = threading.Thread(target=sample_rss, daemon=True)
            sampler.start()
            per_client: list[list[Sample]] = [[] for _ in range(args.clients)]
            threads = [
                threading.Thread(
                    target=client_loop, args=(url, scenes, args, t0, deadline, args.seed + i, per_client[i])
                )
                for i in range(args.clients)
            ]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            elapsed = time.perf_counter() - t0
            stop.set()
            sampler.join()
            for chunk in per_client:
                samples.extend(chunk)
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                exit_code = proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                exit_code = proc.wait()
        load_after = os.getloadavg()
        results = summarise(samples, rss, elapsed)

    try:
        import torch

        threads_note = f", torch {torch.__version__} with {torch.get_num_threads()} threads"
    except ImportError:
        threads_note = ""
    result = {
        "argv": sys.argv[1:] if argv is None else argv,
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "machine": {
            "summary": f"{platform.machine()} Linux, {os.cpu_count()} CPU cores, no GPU{threads_note}",
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "load_average_1min_before_after": [round(load_before[0], 2), round(load_after[0], 2)],
        },
        "config": {
            "clients": args.clients,
            "duration_s": args.duration,
            "width": args.width,
            "height": args.height,
            "quality": args.quality,
            "format": args.format,
        },
        "scenes": [s["id"] for s in scenes],
        "checkpoints_note": note,
        "server_exit_code": exit_code,
        "results": results,
        "notes": [],
    }
    if args.tiny:
        result["notes"].append(
            "The bundled checkpoints (checkpoints/) did not exist yet when this was recorded, so the run "
            "used tiny random models; a trained scene's render cost per frame will differ."
        )
    busy = load_before[0] > (os.cpu_count() or 1)
    result["notes"].append(
        f"1-minute load average before/after the run: {load_before[0]:.2f} / {load_after[0]:.2f} on "
        f"{os.cpu_count()} cores"
        + (
            "; other jobs were running on the machine, so the absolute figures are pessimistic."
            if busy
            else "."
        )
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.out.with_suffix(".json"), result)
    write_markdown(args.out.with_suffix(".md"), result)
    print(json.dumps(results, indent=2))
    return 0 if results["errors"] == 0 and exit_code == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
