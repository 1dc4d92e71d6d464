"""Load test of the render server: concurrent HTTP clients on loopback, two modes.

Each mode starts its own ``visnerf serve`` (a subprocess on a free loopback port, its default
settings), waits until it is ready, runs, and stops it with SIGTERM. Meanwhile it samples the
server's resident memory (VmRSS in /proc/PID/status) four times a second. Every client connects from
its own loopback address (127.0.0.10, .11, ...; the probes from 127.0.0.2 and .3), so that the
server's per-address rate limit sees separate clients, as it would on a network; a client told 429
or 503 waits for its ``Retry-After``.

- ``throughput``: ``--clients`` threads, each with its own ``httpx.Client``, request frames
  (``--width`` x ``--height``, ``--quality``, ``--format``) from random viewpoints and random
  parameter values (so the frame cache rarely answers): ``--warm-up`` seconds unmeasured, then
  ``--rounds`` rounds of ``--duration`` seconds on the same server, the round of median frames per
  second reported (frames per second, latency percentiles, errors, RSS) with every round's figures.
  Targets: 15 frames/s, p95 under 300 ms (128x128 full).
- ``heavy``: two phases of ``--duration`` seconds on one server. In both, a probe asks for
  ``/api/health`` every 0.2 s and another for a 128x128 preview (random view) every 0.5 s; in the
  second, ``--heavy-clients`` anonymous clients also ask, back to back, for the largest full-quality
  frame the server's defaults allow (``--heavy-size``: the largest square within ``max_image_size``
  and ``max_full_pixels``). Side by side: health and preview latency,
  the heavy clients' answers, RSS. Targets: health median under 100 ms, previews p95 under 1 s,
  RSS flat (the last 10 s of a phase within 10 % of its first 10 s). Before the phases the probes
  run ``--warm-up`` seconds alone, unmeasured but for RSS: a fresh server grew from 420 to 638 MB
  over its first 45 s of previews and stayed there for the next three minutes. Phases of 120 s hold
  several 1440x1440 frames (15 to 25 s each); one of 30 s holds about two, and its first 10 s catch
  the first frame's rise (826 to 966 MB in one such run, flat over 120 s).

- ``replicas`` (not part of ``both``): the throughput load through nginx (the shipped
  docker/nginx.conf, on loopback) in front of 1 and then ``--replicas`` servers sharing the
  checkpoints folder, and once straight to one server (nginx's own cost). Through nginx the clients'
  addresses reach the servers in X-Forwarded-For (``VISNERF_TRUSTED_PROXIES=127.0.0.1``).
  Results go to bench/results/server_replicas.json and .md.

- ``bakes``: browsers that draw locally (``GET /api/scenes/{id}/bake``): 8 clients at one setting
  (one bake, then the server's CPU while they orbit) beside the same clients asking for server
  frames, then each at its own setting (bakes a second, the wait for each). Results go to
  bench/results/server_bakes.json and .md.

Results go to bench/results/server_load.json and .md (``replicas``: server_replicas), with the CPU named.

    python bench/server_load.py --duration 120                     # both modes, bundled checkpoints
    python bench/server_load.py --mode throughput --clients 8 --duration 30
    python bench/server_load.py --tiny --mode heavy --duration 10  # tiny random models
    python bench/server_load.py --mode replicas --replicas 2 --rounds 2 --duration 20
    python bench/server_load.py --mode bakes --clients 8 --width 256 --height 256 --duration 30
"""

import visnerf  # noqa: F401  (before torch: it sets the OpenMP wait policy that torch reads once)

# isort: split
import argparse
import dataclasses
import math
import os
import random
import re
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
from bench_common import fmt, load_average, machine_record, markdown_header, write_results

from visnerf.arg_types import positive_int
from visnerf_server.settings import Settings

# Real nginx on loopback with the shipped docker/nginx.conf: its upstream servers and listen port
# replaced by loopback ones, its files (pid, logs, temporaries) in a work folder (``--mode replicas``
# and tests/server/test_replicas_nginx.py).

REPO = Path(__file__).resolve().parents[1]
NGINX_CONF = REPO / "docker" / "nginx.conf"
_UPSTREAM_SERVER = re.compile(r"^(\s*server\s+)server-(\d+):8000(\b[^;\n]*;)\n", re.MULTILINE)
TEMP_PATHS = ("client_body", "proxy", "fastcgi", "uwsgi", "scgi")


def nginx_binary() -> str | None:
    """nginx on PATH, or Debian's /usr/sbin/nginx (not on a user's PATH)."""
    found = shutil.which("nginx")
    if found is None and os.access("/usr/sbin/nginx", os.X_OK):
        found = "/usr/sbin/nginx"
    return found


def local_nginx_conf(upstreams: list[str], listen_port: int, work_dir: Path, template: Path = NGINX_CONF) -> str:
    """The shipped configuration balancing ``upstreams`` (``host:port``) on 127.0.0.1:``listen_port``:
    in each upstream block, the ``server-1`` line for the first and the ``server-2`` line (its
    options kept) for each of the others."""

    def replace(match: re.Match[str]) -> str:
        prefix, number, options = match.groups()
        addresses = upstreams[:1] if number == "1" else upstreams[1:]
        return "".join(f"{prefix}{address}{options}\n" for address in addresses)

    text, found = _UPSTREAM_SERVER.subn(replace, template.read_text())
    if not found:
        raise RuntimeError(f"no `server server-N:8000 ...;` line in {template}")
    text, listens = re.subn(r"listen 8080;", f"listen 127.0.0.1:{listen_port};", text)
    if listens != 1:
        raise RuntimeError(f"no `listen 8080;` in {template}")
    temp = "".join(f"    {name}_temp_path {work_dir / name};\n" for name in TEMP_PATHS)
    text = text.replace("http {\n", "http {\n" + temp, 1)
    text = re.sub(r"proxy_cache_path \S+", f"proxy_cache_path {work_dir / 'bakes'}", text)
    return text.replace("access_log /dev/stdout;", f"access_log {work_dir / 'access.log'};")


def _wait_listening(port: int, process: subprocess.Popen, log: Path, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        if process.poll() is not None:
            raise RuntimeError("nginx exited:\n" + log.read_text(errors="replace"))
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise RuntimeError("nginx is not listening:\n" + log.read_text(errors="replace")) from None
            time.sleep(0.05)


@contextmanager
def running_nginx(binary: str, upstreams: list[str], listen_port: int, work_dir: Path) -> Iterator[str]:
    """nginx in the foreground on the shipped configuration; yields its base URL, stops it with
    SIGQUIT (graceful) or kills it on the way out. Its error log is ``work_dir/error.log``."""
    work_dir.mkdir(parents=True, exist_ok=True)
    conf = work_dir / "nginx.conf"
    conf.write_text(local_nginx_conf(upstreams, listen_port, work_dir))
    error_log = work_dir / "error.log"
    directives = f"daemon off; pid {work_dir / 'nginx.pid'}; error_log {error_log} warn;"
    if os.geteuid() == 0:  # workers would run as nobody, who cannot enter pytest's 0700 folders
        directives += " user root;"
    command = [binary, "-e", str(error_log), "-p", str(work_dir), "-c", str(conf), "-g", directives]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    try:
        _wait_listening(listen_port, process, error_log)
        yield f"http://127.0.0.1:{listen_port}"
    finally:
        process.terminate()  # SIGTERM: fast shutdown
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(10)

ROOT = Path(__file__).resolve().parents[1]
RSS_WINDOW_S = 10.0
RSS_FLAT_FRACTION = 0.10
HEALTH_INTERVAL_S = 0.2
PREVIEW_INTERVAL_S = 0.5
PREVIEW_SIZE = 128
HEALTH_ADDRESS, PREVIEW_ADDRESS = "127.0.0.2", "127.0.0.3"
FIRST_CLIENT_HOST = 10
"""Load client i connects from 127.0.0.(10 + i)."""
TARGETS = {
    "throughput_frames_per_s": 15.0,
    "throughput_p95_ms": 300.0,
    "health_p50_ms": 100.0,
    "preview_p95_ms": 1000.0,
}
THROUGHPUT_ROUNDS = 3
"""Measured rounds of the throughput mode unless ``--rounds`` says otherwise."""


@dataclass
class Sample:
    started: float
    """Seconds since the phase started."""
    latency_ms: float
    status: int
    """HTTP status, or 0 for a transport error (a timeout included)."""


@dataclass
class Phase:
    """What one phase of load recorded, by stream of requests."""

    started: float
    samples: dict[str, list[Sample]] = field(default_factory=dict)
    rss_kb: list[tuple[float, int]] = field(default_factory=list)
    elapsed_s: float = 0.0


# --- the server --------------------------------------------------------------------------------


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


@dataclass
class Server:
    process: subprocess.Popen
    url: str
    scenes: list[dict]
    exit_code: int | None = None


def wait_ready(process: subprocess.Popen, url: str, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"server exited with status {process.returncode} before it was ready")
        try:
            if httpx.get(f"{url}/api/ready", timeout=2).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise RuntimeError("server did not become ready in time")


def stop(process: subprocess.Popen) -> int:
    process.send_signal(signal.SIGTERM)
    try:
        return process.wait(timeout=60)
    except subprocess.TimeoutExpired:
        process.kill()
        return process.wait()


def largest_full_frame() -> int:
    """The side of the largest square full-quality frame the server's default settings allow."""
    defaults = {name: f.default for name, f in Settings.model_fields.items()}
    side = defaults["max_image_size"]
    return min(side, math.isqrt(defaults.get("max_full_pixels", side * side)))


def client_address(index: int) -> str:
    return f"127.0.0.{FIRST_CLIENT_HOST + index}"


@contextmanager
def running_server(checkpoints: Path, log_path: Path, env_extra: dict[str, str] | None = None) -> Iterator[Server]:
    """``visnerf serve`` with its default settings (``env_extra``: some changed); SIGTERM on the way out."""
    port = free_port()
    command = [sys.executable, "-m", "visnerf.cli", "serve", "--host", "127.0.0.1", "--port", str(port),
               "--checkpoints", str(checkpoints), "--no-client", "--log-level", "warning"]  # fmt: skip
    inherited = {k: v for k, v in os.environ.items() if not k.startswith("VISNERF_")}
    env = {**inherited, "VISNERF_TOKEN": "bench-not-used", **(env_extra or {})}
    with log_path.open("wb") as log:
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env)
    url = f"http://127.0.0.1:{port}"
    server = Server(process, url, [])
    try:
        wait_ready(process, url)
        server.scenes = httpx.get(f"{url}/api/scenes").json()
        yield server
    finally:
        server.exit_code = stop(process)


# --- the clients -------------------------------------------------------------------------------


@dataclass(frozen=True)
class FrameAsk:
    """What a render client asks for, every request from a new random view and parameter values."""

    width: int
    height: int
    quality: str
    format: str
    pause_s: float = 0.0
    """Wait between requests (a probe); 0 asks back to back (load)."""
    timeout_s: float = 120.0
    address: str = "127.0.0.1"
    """The loopback address the client connects from: the server's rate limit is per address."""


def random_query(rng: random.Random, scene: dict, ask: FrameAsk) -> dict[str, object]:
    query: dict[str, object] = {
        "azimuth": round(rng.uniform(-180, 180), 3),
        "elevation": round(rng.uniform(-60, 60), 3),
        "width": ask.width,
        "height": ask.height,
        "quality": ask.quality,
        "format": ask.format,
    }
    for axis in scene["params"]:
        query[axis["name"]] = round(rng.uniform(axis["min"], axis["max"]), 4)
    return query


def timed_get(http: httpx.Client, path: str, params: dict | None, t0: float) -> tuple[Sample, float]:
    """One request: its sample, and the seconds the server asked to wait (``Retry-After`` of a 429
    or a 503)."""
    start = time.perf_counter()
    retry_after = 0.0
    try:
        response = http.get(path, params=params)
        response.read()
        status = response.status_code
        if status in (429, 503):
            retry_after = float(response.headers.get("retry-after", "1"))
    except httpx.HTTPError:
        status = 0
    return Sample(start - t0, (time.perf_counter() - start) * 1e3, status), retry_after


def client_from(url: str, address: str, timeout_s: float) -> httpx.Client:
    return httpx.Client(base_url=url, timeout=timeout_s, transport=httpx.HTTPTransport(local_address=address))


def frame_client(server: Server, ask: FrameAsk, seed: int, t0: float, until: float, out: list[Sample]) -> None:
    rng = random.Random(seed)
    with client_from(server.url, ask.address, ask.timeout_s) as http:
        while time.perf_counter() < until:
            scene = rng.choice(server.scenes)
            path = f"/api/scenes/{scene['id']}/render"
            sample, retry_after = timed_get(http, path, random_query(rng, scene, ask), t0)
            out.append(sample)
            time.sleep(max(ask.pause_s, min(retry_after, until - time.perf_counter())))


def health_probe(server: Server, t0: float, until: float, out: list[Sample]) -> None:
    with client_from(server.url, HEALTH_ADDRESS, 30.0) as http:
        while time.perf_counter() < until:
            out.append(timed_get(http, "/api/health", None, t0)[0])
            time.sleep(HEALTH_INTERVAL_S)


def sample_rss(pid: int, t0: float, done: threading.Event, out: list[tuple[float, int]]) -> None:
    while not done.is_set():
        kb = read_rss_kb(pid)
        if kb is not None:
            out.append((time.perf_counter() - t0, kb))
        done.wait(0.25)


def run_phase(server: Server, duration_s: float, streams: dict[str, list[Callable[..., None]]]) -> Phase:
    """Runs every client of every stream (called as ``client(t0, until, samples)``) until the
    deadline and each has finished its last request, sampling the server's RSS meanwhile."""
    t0 = time.perf_counter()
    phase = Phase(started=t0)
    done = threading.Event()
    sampler = threading.Thread(target=sample_rss, args=(server.process.pid, t0, done, phase.rss_kb), daemon=True)
    sampler.start()
    threads = []
    for name, clients in streams.items():
        phase.samples[name] = []
        for client in clients:
            threads.append(threading.Thread(target=client, args=(t0, t0 + duration_s, phase.samples[name])))
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    phase.elapsed_s = time.perf_counter() - t0
    done.set()
    sampler.join()
    return phase


# --- summaries ---------------------------------------------------------------------------------


def percentile(sorted_values: list[float], q: float) -> float:
    if not sorted_values:
        return float("nan")
    index = min(len(sorted_values) - 1, max(0, round(q / 100 * (len(sorted_values) - 1))))
    return sorted_values[index]


def latency_summary(samples: list[Sample], duration_s: float) -> dict[str, Any]:
    ok = sorted(s.latency_ms for s in samples if s.status == 200)
    statuses: dict[str, int] = {}
    for s in samples:
        statuses[str(s.status)] = statuses.get(str(s.status), 0) + 1
    return {
        "requests": len(samples),
        "ok": len(ok),
        "ok_per_s": round(len(ok) / duration_s, 2),
        "latency_ms": {
            "p50": round(percentile(ok, 50), 1),
            "p95": round(percentile(ok, 95), 1),
            "p99": round(percentile(ok, 99), 1),
            "mean": round(statistics.fmean(ok), 1) if ok else None,
            "max": round(ok[-1], 1) if ok else None,
        },
        "errors": sum(1 for s in samples if s.status not in (200, 429, 503)),
        "status_429": statuses.get("429", 0),
        "status_503": statuses.get("503", 0),
        "status_counts": statuses,
    }


def rss_summary(rss: list[tuple[float, int]], duration_s: float) -> dict[str, Any]:
    first = [kb for t, kb in rss if t <= RSS_WINDOW_S]
    last = [kb for t, kb in rss if t >= duration_s - RSS_WINDOW_S]

    def mb(values: list[int], reduce: Callable[[list[int]], float]) -> float | None:
        return round(reduce(values) / 1024, 1) if values else None

    first_mean, last_mean = mb(first, statistics.fmean), mb(last, statistics.fmean)
    growth = (last_mean - first_mean) / first_mean if first_mean and last_mean is not None else None
    return {
        "peak": mb([kb for _, kb in rss], max),
        "first_10s_mean": first_mean,
        "last_10s_mean": last_mean,
        "growth_fraction": round(growth, 3) if growth is not None else None,
        "flat": growth is not None and growth <= RSS_FLAT_FRACTION,
        "samples": len(rss),
    }


def phase_summary(phase: Phase) -> dict[str, Any]:
    summary: dict[str, Any] = {"elapsed_s": round(phase.elapsed_s, 1)}
    summary.update({name: latency_summary(samples, phase.elapsed_s) for name, samples in phase.samples.items()})
    summary["rss_mb"] = rss_summary(phase.rss_kb, phase.elapsed_s)
    return summary


# --- the two modes -----------------------------------------------------------------------------


def throughput_mode(args: argparse.Namespace, checkpoints: Path, work: Path) -> dict[str, Any]:
    """``--warm-up`` seconds of the load unmeasured (a fresh server compiles its loops and reads
    each scene's tables on its first frames), then ``--rounds`` measured rounds of ``--duration``
    seconds on the same server; the round of median frames per second is the result (this figure
    swung by up to 25 % between runs a minute apart on one machine) and judges the targets."""
    asks = [
        FrameAsk(args.width, args.height, args.quality, args.format, timeout_s=max(60.0, args.duration),
                 address=client_address(i))
        for i in range(args.clients)
    ]
    rounds = THROUGHPUT_ROUNDS if args.rounds is None else args.rounds
    with running_server(checkpoints, work / "throughput.log") as server:
        def clients(seed: int) -> list[Callable[..., None]]:
            return [lambda t0, until, out, ask=ask, seed=seed + i: frame_client(server, ask, seed, t0, until, out)
                    for i, ask in enumerate(asks)]

        if args.warm_up > 0:
            run_phase(server, args.warm_up, {"frames": clients(args.seed + 1000)})
        summaries = [phase_summary(run_phase(server, args.duration, {"frames": clients(args.seed + 100 * r)}))
                     for r in range(rounds)]
    by_rate = sorted(summaries, key=lambda s: s["frames"]["ok_per_s"])
    summary = by_rate[(len(by_rate) - 1) // 2]  # the median round (the lower middle one of an even count)
    frames = summary["frames"]
    return {
        "config": {"clients": args.clients, "duration_s": args.duration, "width": args.width,
                   "height": args.height, "quality": args.quality, "format": args.format,
                   "warm_up_s": args.warm_up, "rounds": rounds},
        "scenes": [s["id"] for s in server.scenes],
        "server_exit_code": server.exit_code,
        "results": summary,
        "rounds": [{"frames_per_s": s["frames"]["ok_per_s"], "p50_ms": s["frames"]["latency_ms"]["p50"],
                    "p95_ms": s["frames"]["latency_ms"]["p95"]} for s in summaries],
        "meets_targets": {
            "frames_per_s": frames["ok_per_s"] >= TARGETS["throughput_frames_per_s"],
            "p95": frames["latency_ms"]["p95"] < TARGETS["throughput_p95_ms"],
        },
    }


def probes(server: Server, seed: int) -> dict[str, list[Callable[..., None]]]:
    preview = FrameAsk(PREVIEW_SIZE, PREVIEW_SIZE, "preview", "jpeg", PREVIEW_INTERVAL_S, address=PREVIEW_ADDRESS)
    return {
        "health": [lambda t0, until, out: health_probe(server, t0, until, out)],
        "preview": [lambda t0, until, out: frame_client(server, preview, seed, t0, until, out)],
    }


def heavy_mode(args: argparse.Namespace, checkpoints: Path, work: Path) -> dict[str, Any]:
    size = args.heavy_size
    asks = [FrameAsk(size, size, "full", "jpeg", timeout_s=300.0, address=client_address(i))
            for i in range(args.heavy_clients)]
    with running_server(checkpoints, work / "heavy.log") as server:
        warm_up = run_phase(server, args.warm_up, probes(server, args.seed + 2)) if args.warm_up > 0 else None
        quiet = run_phase(server, args.duration, probes(server, args.seed))
        clients = [
            lambda t0, until, out, ask=ask, seed=args.seed + 100 + i: frame_client(server, ask, seed, t0, until, out)
            for i, ask in enumerate(asks)
        ]
        loaded = run_phase(server, args.duration, {**probes(server, args.seed + 1), "heavy": clients})
    phases = {"quiet": phase_summary(quiet), "loaded": phase_summary(loaded)}
    warm_rss = [kb for _, kb in warm_up.rss_kb] if warm_up is not None else []
    return {
        "warm_up_rss_mb": {"first": round(warm_rss[0] / 1024, 1), "last": round(warm_rss[-1] / 1024, 1)} if warm_rss else None,
        "config": {"heavy_clients": args.heavy_clients, "heavy_frame": f"{size}x{size} full jpeg",
                   "warm_up_s": args.warm_up,
                   "duration_s_per_phase": args.duration, "health_every_s": HEALTH_INTERVAL_S,
                   "preview": f"{PREVIEW_SIZE}x{PREVIEW_SIZE} preview jpeg every {PREVIEW_INTERVAL_S} s"},
        "scenes": [s["id"] for s in server.scenes],
        "server_exit_code": server.exit_code,
        "phases": phases,
        "meets_targets": {
            name: {
                "health_p50": p["health"]["latency_ms"]["p50"] < TARGETS["health_p50_ms"],
                "preview_p95": p["preview"]["ok"] > 0 and p["preview"]["latency_ms"]["p95"] < TARGETS["preview_p95_ms"],
                "rss_flat": p["rss_mb"]["flat"],
            }
            for name, p in phases.items()
        },
    }


def replica_runs(replicas: int) -> list[dict[str, Any]]:
    """What ``replicas`` mode measures: one server straight, then behind nginx 1 and ``replicas``
    servers with their default threads, and ``replicas`` servers sharing the cores between them."""
    shared_threads = max(1, (os.cpu_count() or 1) // replicas)
    return [
        {"label": "1 server, no proxy", "replicas": 1, "nginx": False, "threads": None},
        {"label": "nginx + 1 server", "replicas": 1, "nginx": True, "threads": None},
        {"label": f"nginx + {replicas} servers", "replicas": replicas, "nginx": True, "threads": None},
        {"label": f"nginx + {replicas} servers, {shared_threads} thread(s) each", "replicas": replicas,
         "nginx": True, "threads": shared_threads},
    ]


def replicas_mode(args: argparse.Namespace, checkpoints: Path, work: Path, nginx: str) -> dict[str, Any]:
    """Each setup ``--rounds`` times, every other round in reverse order (drifting load on a shared
    machine weighs on every setup alike); the report gives each setup's median."""
    setups = replica_runs(args.replicas)
    rounds = 1 if args.rounds is None else args.rounds
    order = [(r, s) for r in range(rounds) for s in (setups if r % 2 == 0 else setups[::-1])]
    runs = []
    for i, (round_index, run) in enumerate(order):
        env = {"VISNERF_TRUSTED_PROXIES": "127.0.0.1"}
        if run["threads"] is not None:
            env["VISNERF_THREADS"] = str(run["threads"])
        with ExitStack() as stack:
            servers = [stack.enter_context(running_server(checkpoints, work / f"replicas-{i}-{r}.log", env))
                       for r in range(run["replicas"])]
            target = servers[0]
            if run["nginx"]:
                upstreams = [s.url.removeprefix("http://") for s in servers]
                url = stack.enter_context(running_nginx(nginx, upstreams, free_port(), work / f"nginx-{i}"))
                target = dataclasses.replace(servers[0], url=url)
            asks = [FrameAsk(args.width, args.height, args.quality, args.format, timeout_s=max(60.0, args.duration),
                             address=client_address(c)) for c in range(args.clients)]
            clients = [
                lambda t0, until, out, ask=ask, seed=args.seed + c, to=target: frame_client(to, ask, seed, t0, until, out)
                for c, ask in enumerate(asks)
            ]
            phase = run_phase(target, args.duration, {"frames": clients})
        runs.append({**run, "round": round_index, "load_average_1min": load_average(),
                     "results": latency_summary(phase.samples["frames"], phase.elapsed_s),
                     "server_exit_codes": [s.exit_code for s in servers]})
    return {
        "config": {"clients": args.clients, "duration_s": args.duration, "width": args.width, "height": args.height,
                   "quality": args.quality, "format": args.format, "replicas": args.replicas, "rounds": rounds},
        "scenes": [s["id"] for s in servers[0].scenes],
        "runs": runs,
    }


def replicas_markdown(path: Path, record: dict[str, Any]) -> None:
    mode = record["replicas"]
    c = mode["config"]
    lines = markdown_header("Render server replicas behind nginx", record)
    lines += [
        "",
        f"The throughput load ({c['clients']} clients, each from its own loopback address, {c['duration_s']} s, "
        f"{c['width']}x{c['height']} {c['quality']} {c['format']}, random view and parameter values; scenes "
        f"{', '.join(mode['scenes'])}) against one `visnerf serve`, then through nginx (docker/nginx.conf on "
        f"loopback, {record['nginx']}) in front of 1 and {c['replicas']} servers sharing the checkpoints folder. "
        "Servers, nginx and clients share the machine's cores.",
        f"Server defaults: {record['server_defaults']}.",
        "",
        f"Each setup ran {c['rounds']} time(s), every other round in reverse order; medians first, then every run "
        "in the order it ran, with the 1-min load average after it.",
        "",
        "| setup | frames per second, median (each run) | latency p50 / p95, median (ms) |",
        "| --- | --- | --- |",
    ]
    labels = list(dict.fromkeys(run["label"] for run in mode["runs"]))
    for label in labels:
        runs = [run for run in mode["runs"] if run["label"] == label]
        fps = [run["results"]["ok_per_s"] for run in runs]
        p50 = statistics.median(run["results"]["latency_ms"]["p50"] for run in runs)
        p95 = statistics.median(run["results"]["latency_ms"]["p95"] for run in runs)
        lines.append(f"| {label} | {statistics.median(fps):.2f} ({', '.join(str(f) for f in fps)}) | "
                     f"{fmt(p50)} / {fmt(p95)} |")
    lines += [
        "",
        "| round | setup | frames per second | latency p50 / p95 / p99 (ms) | answers | load average after | "
        "servers' exit status |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for run in mode["runs"]:
        r, lat = run["results"], run["results"]["latency_ms"]
        lines.append(f"| {run['round'] + 1} | {run['label']} | {r['ok_per_s']} | {fmt(lat['p50'])} / {fmt(lat['p95'])} / "
                     f"{fmt(lat['p99'])} | {statuses(r)} | {run['load_average_1min']} | "
                     f"{', '.join(str(code) for code in run['server_exit_codes'])} |")
    lines.append("")
    if record.get("notes"):
        lines += ["Notes:", ""] + [f"- {n}" for n in record["notes"]] + [""]
    path.write_text("\n".join(lines))


# --- bakes --------------------------------------------------------------------------------------


def cpu_seconds(pid: int) -> float:
    """User and system CPU seconds a process has used (/proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def fetch_bake(http: httpx.Client, scene: str, params: dict[str, float], limit_s: float) -> tuple[float, int, int]:
    """(seconds until the bake came, its status, the 503s answered meanwhile): the browser's
    loop, asking again after each Retry-After."""
    start, waits = time.perf_counter(), 0
    while True:
        response = http.get(f"/api/scenes/{scene}/bake", params=params)
        if response.status_code != 503 or time.perf_counter() - start > limit_s:
            return time.perf_counter() - start, response.status_code, waits
        waits += 1
        time.sleep(float(response.headers.get("retry-after", "1")))


def bakes_mode(args: argparse.Namespace, checkpoints: Path, work: Path) -> dict[str, Any]:
    """Eight browsers drawing locally: at one setting (each fetches the one bake, then orbits with
    no request: the server's CPU seconds over ``--duration`` after it), beside the same clients
    asking the server for full frames at that setting; then each at its own setting (a new random
    setting as each bake arrives: bakes a second, the wait from a slider settling to its bake)."""
    clients = args.clients
    out: dict[str, Any] = {"config": {"clients": clients, "duration_s": args.duration, "width": args.width,
                                      "height": args.height}}
    with running_server(checkpoints, work / "bakes.log") as server:
        scene = next(s for s in server.scenes if s["id"] == args.bake_scene)
        defaults = {a["name"]: a["default"] for a in scene["params"]}
        pid = server.process.pid
        # today's path: full frames at one setting from random views, the server's CPU meanwhile
        ask = [FrameAsk(args.width, args.height, "full", "png", address=client_address(i)) for i in range(clients)]
        fixed = {**scene, "params": [{**a, "min": a["default"], "max": a["default"]} for a in scene["params"]]}
        one = Server(server.process, server.url, [fixed])
        run_phase(one, min(args.warm_up, 10.0), {"frames": [
            lambda t0, until, o, a=a, i=i: frame_client(one, a, args.seed + i, t0, until, o) for i, a in enumerate(ask)]})
        before = cpu_seconds(pid)
        phase = run_phase(one, args.duration, {"frames": [
            lambda t0, until, o, a=a, i=i: frame_client(one, a, args.seed + 50 + i, t0, until, o)
            for i, a in enumerate(ask)]})
        frames = latency_summary(phase.samples["frames"], phase.elapsed_s)
        out["server_frames"] = {"frames_per_s_each": round(frames["ok_per_s"] / clients, 2),
                                "p95_ms": frames["latency_ms"]["p95"],
                                "server_cpu_s_per_s": round((cpu_seconds(pid) - before) / phase.elapsed_s, 2)}
        # the bake of that setting: every client asks at once, one build serves them all
        firsts: list[tuple[float, int, int]] = []
        before = cpu_seconds(pid)

        def first_bake(i: int) -> None:
            with client_from(server.url, client_address(i), 120.0) as http:
                firsts.append(fetch_bake(http, scene["id"], defaults, 120.0))

        threads = [threading.Thread(target=first_bake, args=(i,)) for i in range(clients)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        build_cpu = cpu_seconds(pid) - before
        before = cpu_seconds(pid)
        time.sleep(args.duration)  # the clients orbit, drawing in their browsers: nothing reaches the server
        out["one_setting"] = {
            "first_bake_s": {"p50": round(statistics.median(f[0] for f in firsts), 2),
                             "max": round(max(f[0] for f in firsts), 2)},
            "statuses": sorted({f[1] for f in firsts}), "build_cpu_s": round(build_cpu, 2),
            "server_cpu_s_per_s_orbiting": round((cpu_seconds(pid) - before) / args.duration, 3),
        }
        # each client at its own setting, a new one as each bake arrives
        waits: list[float] = []
        statuses_seen: dict[str, int] = {}
        t0 = time.perf_counter()

        def own_settings(i: int) -> None:
            rng = random.Random(args.seed + 200 + i)
            with client_from(server.url, client_address(i), 120.0) as http:
                while time.perf_counter() - t0 < args.duration:
                    params = {a["name"]: round(rng.uniform(a["min"], a["max"]), 4) for a in scene["params"]}
                    seconds, status, _ = fetch_bake(http, scene["id"], params, 120.0)
                    statuses_seen[str(status)] = statuses_seen.get(str(status), 0) + 1
                    if status == 200:
                        waits.append(seconds * 1e3)

        threads = [threading.Thread(target=own_settings, args=(i,)) for i in range(clients)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        elapsed = time.perf_counter() - t0
        ordered = sorted(waits)
        out["own_settings"] = {"bakes_per_s": round(len(waits) / elapsed, 2), "bakes": len(waits),
                               "wait_ms": {"p50": round(percentile(ordered, 50), 1), "p95": round(percentile(ordered, 95), 1)},
                               "statuses": statuses_seen, "elapsed_s": round(elapsed, 1)}
        out["scene"] = scene["id"]
    out["server_exit_code"] = server.exit_code
    return out


def bakes_markdown(path: Path, record: dict[str, Any]) -> None:
    mode = record["bakes"]
    c = mode["config"]
    server, one, own = mode["server_frames"], mode["one_setting"], mode["own_settings"]
    lines = markdown_header("Bakes under load: browsers that draw locally", record)
    lines += [
        "", f"{c['clients']} clients, each from its own loopback address, on `{mode['scene']}`; "
        f"{c['duration_s']} s a phase. Server defaults: {record['server_defaults']}.", "",
        "| at one setting | frames a second each client sees | server CPU seconds a second |", "| --- | --- | --- |",
        f"| server frames ({c['width']}x{c['height']} full PNG, random views) | {server['frames_per_s_each']} "
        f"(p95 {fmt(server['p95_ms'])} ms) | {server['server_cpu_s_per_s']} |",
        f"| local frames, after one bake (first bake p50 {one['first_bake_s']['p50']} s, last {one['first_bake_s']['max']} s, "
        f"{one['build_cpu_s']} CPU s to build) | every animation frame, on the client's GPU "
        f"([local_frames.md](local_frames.md)) | {one['server_cpu_s_per_s_orbiting']} |", "",
        "| each client at its own setting | bakes a second | wait from a settled slider to its bake, p50 / p95 (ms) |",
        "| --- | --- | --- |",
        f"| a new random setting as each bake arrives | {own['bakes_per_s']} ({own['bakes']} bakes) | "
        f"{fmt(own['wait_ms']['p50'])} / {fmt(own['wait_ms']['p95'])} |", "",
    ]
    if record.get("notes"):
        lines += ["Notes:", ""] + [f"- {n}" for n in record["notes"]] + [""]
    path.write_text("\n".join(lines))


# --- the report --------------------------------------------------------------------------------


def yes_no(value: bool) -> str:
    return "yes" if value else "**no**"


def statuses(summary: dict[str, Any]) -> str:
    return ", ".join(f"{code}: {n}" for code, n in sorted(summary["status_counts"].items())) or "-"


def throughput_lines(mode: dict[str, Any]) -> list[str]:
    c, r = mode["config"], mode["results"]
    frames, rss, met = r["frames"], r["rss_mb"], mode["meets_targets"]
    lat = frames["latency_ms"]
    rounds = mode.get("rounds", [])
    repeat = ""
    if rounds:
        each = "; ".join(f"{one['frames_per_s']} frames/s, p50 {fmt(one['p50_ms'])}, p95 {fmt(one['p95_ms'])} ms"
                         for one in rounds)
        repeat = (f" After {c.get('warm_up_s', 0):g} s of the same load unmeasured, {len(rounds)} round(s) on the "
                  f"same server ({each}); the table gives the round of median frames per second.")
    return [
        "## Throughput",
        "",
        f"{c['clients']} clients for {c['duration_s']} s, {c['width']}x{c['height']} {c['quality']} "
        f"{c['format']}, random view and parameter values; scenes {', '.join(mode['scenes'])}; "
        f"server exit status after SIGTERM {mode['server_exit_code']}.{repeat}",
        "",
        "| measure | value | target |",
        "| --- | --- | --- |",
        f"| frames per second | {frames['ok_per_s']} | {TARGETS['throughput_frames_per_s']:g} "
        f"({yes_no(met['frames_per_s'])}) |",
        f"| latency p50 / p95 / p99 (ms) | {fmt(lat['p50'])} / {fmt(lat['p95'])} / {fmt(lat['p99'])} | "
        f"p95 < {TARGETS['throughput_p95_ms']:g} ({yes_no(met['p95'])}) |",
        f"| latency mean / max (ms) | {fmt(lat['mean'])} / {fmt(lat['max'])} | |",
        f"| answers | {statuses(frames)} | |",
        f"| server RSS first 10 s / last 10 s mean, peak (MB) | {fmt(rss['first_10s_mean'])} / "
        f"{fmt(rss['last_10s_mean'])}, {fmt(rss['peak'])} | flat ({yes_no(rss['flat'])}) |",
        "",
    ]


def warm_up_line(mode: dict[str, Any]) -> str:
    """What the probes' unmeasured warm-up did to a fresh server's RSS (older records had none)."""
    warm, seconds = mode.get("warm_up_rss_mb"), mode["config"].get("warm_up_s", 0)
    if not warm:
        return ""
    return (f"First the probes alone for {seconds:g} s, not measured: a fresh server's first frames of each "
            f"scene (RSS {fmt(warm['first'])} to {fmt(warm['last'])} MB). ")


def heavy_lines(mode: dict[str, Any]) -> list[str]:
    c, quiet, loaded = mode["config"], mode["phases"]["quiet"], mode["phases"]["loaded"]
    met = mode["meets_targets"]

    def row(label: str, value: Callable[[dict[str, Any]], str], target: str = "") -> str:
        return f"| {label} | {value(quiet)} | {value(loaded)} | {target} |"

    def lat(stream: str, q: str) -> Callable[[dict[str, Any]], str]:
        return lambda p: fmt(p[stream]["latency_ms"][q]) if stream in p else "-"

    heavy = loaded["heavy"]
    return [
        "## Heavy clients",
        "",
        f"{warm_up_line(mode)}Two phases of {c['duration_s_per_phase']} s on one server: probes alone, then probes beside "
        f"{c['heavy_clients']} anonymous clients, each from its own address, asking back to back for the "
        f"largest full frame allowed ({c['heavy_frame']}), waiting out each 429's or 503's Retry-After. "
        f"Probes: `/api/health` every {c['health_every_s']} s, a {c['preview']}. "
        f"Scenes {', '.join(mode['scenes'])}; server exit status after SIGTERM {mode['server_exit_code']}.",
        "",
        "| measure | probes alone | with heavy clients | target (met alone / loaded) |",
        "| --- | --- | --- | --- |",
        row("health p50 / p95 / max (ms)", lambda p: f"{lat('health', 'p50')(p)} / {lat('health', 'p95')(p)} / "
            f"{lat('health', 'max')(p)}", f"p50 < {TARGETS['health_p50_ms']:g} ({yes_no(met['quiet']['health_p50'])} / "
            f"{yes_no(met['loaded']['health_p50'])})"),
        row("health answers", lambda p: statuses(p["health"])),
        row("preview p50 / p95 / max (ms)", lambda p: f"{lat('preview', 'p50')(p)} / {lat('preview', 'p95')(p)} / "
            f"{lat('preview', 'max')(p)}", f"p95 < {TARGETS['preview_p95_ms']:g} "
            f"({yes_no(met['quiet']['preview_p95'])} / {yes_no(met['loaded']['preview_p95'])})"),
        row("preview answers", lambda p: statuses(p["preview"])),
        row("server RSS first 10 s / last 10 s mean (MB)",
            lambda p: f"{fmt(p['rss_mb']['first_10s_mean'])} / {fmt(p['rss_mb']['last_10s_mean'])}",
            f"flat, within {RSS_FLAT_FRACTION:.0%} ({yes_no(met['quiet']['rss_flat'])} / "
            f"{yes_no(met['loaded']['rss_flat'])})"),
        row("server RSS peak (MB)", lambda p: fmt(p["rss_mb"]["peak"])),
        "",
        f"Heavy clients: {heavy['ok']} frames in {loaded['elapsed_s']} s (the phase runs until each client's "
        f"last request is answered), latency p50 {fmt(heavy['latency_ms']['p50'])} ms, max "
        f"{fmt(heavy['latency_ms']['max'])} ms; answers {statuses(heavy)}.",
        "",
    ]


def write_markdown(path: Path, record: dict[str, Any]) -> None:
    lines = markdown_header("Render server load test", record)
    lines += ["", "Each mode starts its own `visnerf serve` with its default settings on loopback; the clients "
              "run on the same machine, each from its own loopback address (the rate limit is per address).",
              f"Server defaults: {record['server_defaults']}.", ""]
    if "throughput" in record:
        lines += throughput_lines(record["throughput"])
    if "heavy" in record:
        lines += heavy_lines(record["heavy"])
    if record.get("notes"):
        lines += ["Notes:", ""] + [f"- {n}" for n in record["notes"]] + [""]
    path.write_text("\n".join(lines))


# --- main --------------------------------------------------------------------------------------


def server_defaults() -> str:
    """The defaults that shape these figures (read from the server's settings)."""
    names = ("render_workers", "preview_workers", "render_queue_size", "render_timeout_s", "max_image_size", "max_full_pixels",
             "max_preview_pixels", "rate_limit_pixels_per_s", "rate_limit_burst_pixels", "threads")
    fields = Settings.model_fields
    return ", ".join(f"{name} {fields[name].default}" for name in names if name in fields)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mode", choices=["throughput", "heavy", "both", "replicas", "bakes"], default="both")
    parser.add_argument("--bake-scene", default="vortex_tf1", help="bakes mode: the scene the clients explore")
    parser.add_argument("--duration", type=float, default=30.0, help="seconds of each phase")
    parser.add_argument("--warm-up", type=float, default=30.0,
                        help="seconds before the measured phases, unmeasured: the heavy mode's probes alone (RSS "
                             "reported apart), the throughput mode's load (0: none)")
    parser.add_argument("--checkpoints", type=Path, default=ROOT / "checkpoints")
    parser.add_argument("--tiny", action="store_true", help="serve tiny random checkpoints made for the run")
    parser.add_argument("--clients", type=int, default=4, help="throughput mode: concurrent clients")
    parser.add_argument("--width", type=int, default=128)
    parser.add_argument("--height", type=int, default=128)
    parser.add_argument("--quality", choices=["preview", "full"], default="full")
    parser.add_argument("--format", choices=["png", "jpeg", "webp"], default="jpeg")
    parser.add_argument("--heavy-clients", type=int, default=4, help="heavy mode: clients asking for the largest frame")
    parser.add_argument("--heavy-size", type=int, default=largest_full_frame(),
                        help="side of the square frames the heavy clients ask for (default: the largest allowed)")
    parser.add_argument("--replicas", type=int, default=2, help="replicas mode: servers behind nginx to compare with one")
    parser.add_argument("--rounds", type=positive_int, default=None,
                        help=f"measured rounds of the throughput load on its server (default {THROUGHPUT_ROUNDS}), or "
                             "times each replicas setup runs (default 1); medians reported")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results")
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    record: dict[str, Any] = {**machine_record(), "command": "python bench/server_load.py " + " ".join(
        sys.argv[1:] if argv is None else argv), "server_defaults": server_defaults(), "notes": []}
    load = {"before": round(load_average(), 2)}
    with tempfile.TemporaryDirectory(prefix="visnerf-load-") as tmp:
        work = Path(tmp)
        checkpoints = args.checkpoints
        if args.tiny:
            checkpoints = work / "checkpoints"
            checkpoints.mkdir()
            make_tiny_checkpoints(checkpoints)
            record["notes"].append("Tiny random checkpoints (visnerf.testing.make_tiny_checkpoint, 8^3 grids).")
        elif not any(checkpoints.glob("*.safetensors")):
            print(f"no checkpoints in {checkpoints}; use --tiny or --checkpoints DIR", file=sys.stderr)
            return 2
        if args.mode in ("throughput", "both"):
            record["throughput"] = throughput_mode(args, checkpoints, work)
            load["between"] = round(load_average(), 2)
        if args.mode in ("heavy", "both"):
            record["heavy"] = heavy_mode(args, checkpoints, work)
        if args.mode == "bakes":
            record["bakes"] = bakes_mode(args, checkpoints, work)
        if args.mode == "replicas":
            binary = nginx_binary()
            if binary is None:
                print("nginx is not installed (apt-get install nginx)", file=sys.stderr)
                return 2
            record["nginx"] = subprocess.run([binary, "-v"], capture_output=True, text=True).stderr.strip()
            record["replicas"] = replicas_mode(args, checkpoints, work, binary)
    load["after"] = round(load_average(), 2)
    record["load_average_1min"] = load
    record["notes"].append(
        "The machine record's torch threads are the load generator's; the server picks its own. Load generator "
        "and server share the machine's cores."
    )
    if args.mode == "replicas":
        cores = os.cpu_count() or 1
        if max(load.values()) > cores:
            record["notes"].append(
                f"The 1-min load average passed the {cores} cores: other work on the machine competed with the "
                "servers, and the runs, made one after the other, may not have met the same competition."
            )
        write_results(args.out, "server_replicas", record, replicas_markdown)
        exits = [code for run in record["replicas"]["runs"] for code in run["server_exit_codes"]]
        return 0 if all(code == 0 for code in exits) else 1
    if args.mode == "bakes":
        write_results(args.out, "server_bakes", record, bakes_markdown)
        return 0 if record["bakes"]["server_exit_code"] == 0 else 1
    write_results(args.out, "server_load", record, write_markdown)
    exits = [record[m]["server_exit_code"] for m in ("throughput", "heavy") if m in record]
    return 0 if all(code == 0 for code in exits) else 1


if __name__ == "__main__":
    sys.exit(main())
