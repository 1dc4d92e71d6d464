"""Movie speed: frames per second of `visnerf animate` on bundled scenes and a Nyx model.

For each checkpoint and size, the orbit `visnerf animate CKPT --orbit N --size SxS -o movie.mp4`
renders (one turn at the scene's default camera and parameters) is rendered and encoded to H.264
exactly as the command does (``animation.movie.render_frames`` into ``write_movie``), after one
untimed frame. Records frames per second of the whole job, the median render time of a frame and
the share of the time spent encoding; the movie is decoded back to check its frame count.

    .venv/bin/python bench/movie_speed.py --threads 2
    .venv/bin/python bench/movie_speed.py --checkpoints checkpoints/tangle_iso.safetensors \\
        runs/nyx.safetensors --sizes 256,512 --frames 24

Then, in `visnerf serve` with the bundled checkpoints: interactive renders (128x128 previews and
256x256 full frames of `--server-scene`, one probe client each, a request every 0.3 s) for
`--server-seconds` with the server idle, then as long again while a movie job (an orbit of
`--server-frames` frames at 256x256) renders on the same server; their median and p95 latency in
both phases, and the job's own frames per second. Writes movie_speed.json and movie_speed.md to
--out-dir (bench/results).
"""

import visnerf  # noqa: F401  (before torch: it sets the OpenMP wait policy that torch reads once)

# isort: split
import argparse
import dataclasses
import json
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import av
import httpx

from visnerf import runtime
from visnerf.animation.interpolation import sample_frames
from visnerf.animation.movie import MovieSettings, render_frames, write_movie
from visnerf.animation.presets import orbit_path
from visnerf.inference import load_scene

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_common import machine_record  # noqa: E402
from server_load import FrameAsk, Sample, frame_client, latency_summary, running_server  # noqa: E402

PROBE_PAUSE_S = 0.3
PROBES = {"preview": FrameAsk(128, 128, "preview", "jpeg", pause_s=PROBE_PAUSE_S, address="127.0.0.3"),
          "full": FrameAsk(256, 256, "full", "jpeg", pause_s=PROBE_PAUSE_S, address="127.0.0.4")}
"""The interactive clients, each from its own loopback address (the rate limit is per address)."""


def orbit_frames(scene, n_frames: int, fps: float) -> list:
    """The frames of `visnerf animate CKPT --orbit N`: one turn from the scene's default camera,
    at its default parameters."""
    cam = scene.info.camera
    params = {a.name: a.default for a in scene.info.params}
    path = orbit_path(n_frames, fps, float(cam.get("elevation", 0.0)), float(cam.get("distance", 2.0)),
                      float(cam.get("fov_deg", 30.0)), params, start_azimuth=float(cam.get("azimuth", 0.0)))
    return sample_frames(path, fps, scene.info.params)


def measure(checkpoint: Path, size: int, n_frames: int, fps: float, work: Path) -> dict:
    """Render and encode one orbit movie; time each frame's render and the whole job."""
    scene = load_scene(checkpoint)
    frames = orbit_frames(scene, n_frames, fps)
    settings = MovieSettings(fps=fps, width=size, height=size, format="mp4")
    first = frames[0]
    scene.render(first.c2w, first.fov_deg, size, size, first.params, "full")  # untimed: warm-up
    render_s: list[float] = []

    def timed_frames():
        """``render_frames``, as `visnerf animate` renders, with the time of each frame kept."""
        rendered = render_frames(scene, frames, settings)
        while True:
            t0 = time.perf_counter()
            try:
                image = next(rendered)
            except StopIteration:
                return
            render_s.append(time.perf_counter() - t0)
            yield image

    out = work / f"{checkpoint.stem}_{size}.mp4"
    t0 = time.perf_counter()
    result = write_movie(timed_frames(), out, settings, len(frames))
    total_s = time.perf_counter() - t0
    with av.open(str(out)) as container:
        decoded = sum(1 for _ in container.decode(video=0))
    return {
        "checkpoint": str(checkpoint.relative_to(ROOT) if checkpoint.is_relative_to(ROOT) else checkpoint),
        "size": size, "frames": result.frames_written, "decoded_frames": decoded, "seconds": total_s,
        "frames_per_second": result.frames_written / total_s, "render_ms_median": 1000 * statistics.median(render_s),
        "encode_share": max(0.0, 1.0 - sum(render_s) / total_s), "mp4_kb": out.stat().st_size / 1024,
    }  # fmt: skip


def probe_phase(server, scene_id: str, seconds: float, seed: int) -> dict[str, list[Sample]]:
    """The probe clients, asking only for ``scene_id``, for ``seconds``; random views and parameter
    values from ``seed`` (each phase its own, so that no phase reads frames another left in the
    server's frame cache)."""
    only = [sc for sc in server.scenes if sc["id"] == scene_id]
    if not only:
        raise SystemExit(f"error: the server has no scene {scene_id!r}: {[sc['id'] for sc in server.scenes]}")
    view = dataclasses.replace(server, scenes=only)
    t0 = time.perf_counter()
    samples: dict[str, list[Sample]] = {name: [] for name in PROBES}
    threads = [threading.Thread(target=frame_client, args=(view, ask, seed + i, t0, t0 + seconds, samples[name]))
               for i, (name, ask) in enumerate(PROBES.items())]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return samples


def server_phases(scene_id: str, frames: int, seconds: float, work: Path) -> dict:
    """Interactive latency idle, then beside a movie job of ``frames`` frames; the job's speed."""
    with running_server(ROOT / "checkpoints", work / "server.log") as server:
        probe_phase(server, scene_id, min(seconds, 10.0), seed=100)  # untimed: first renders
        idle = probe_phase(server, scene_id, seconds, seed=200)
        with httpx.Client(base_url=server.url, timeout=60, transport=httpx.HTTPTransport(local_address="127.0.0.5")) as http:
            created = http.post(f"/api/scenes/{scene_id}/movies",
                                json={"orbit": frames, "fps": 24, "width": 256, "height": 256, "format": "mp4"})
            if created.status_code != 202:
                raise SystemExit(f"error: the movie job was refused: {created.status_code} {created.text}")
            job = created.json()
            t_job = time.perf_counter()
            busy = probe_phase(server, scene_id, seconds, seed=300)
            while (status := http.get(job["status_url"]).json())["state"] in ("queued", "running"):
                time.sleep(0.5)
            job_s = time.perf_counter() - t_job
            mp4 = http.get(job["file_url"])
    summary = {phase: {name: latency_summary(samples, seconds) for name, samples in probes.items()}
               for phase, probes in (("idle", idle), ("with_movie_job", busy))}
    return {"scene": scene_id, "seconds_per_phase": seconds, "job_frames": frames, "job_state": status["state"],
            "job_seconds": job_s, "job_frames_per_second": status["frames_done"] / job_s,
            "job_mp4_kb": len(mp4.content) / 1024, "probes": summary}


def write_markdown(path: Path, record: dict) -> None:
    lines = ["# Movie speed: `visnerf animate`", "",
             f"Command: `{record['command']}`  ", f"Machine: {record['machine']}, {record['torch_threads']} torch "
             f"thread(s), torch {record['torch']}, {record['date']}.", "",
             f"Each row: an orbit of {record['frames']} frames at the scene's default camera and parameters, full "
             "quality, rendered and encoded to H.264 as `visnerf animate --orbit` does, after one untimed frame.", "",
             "| checkpoint | size | frames per second | render ms a frame (median) | encoding share | MP4 KB | frames decoded |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in record["rows"]:
        if "error" in r:
            lines.append(f"| {r['checkpoint']} | {r['size']} | skipped: {r['error']} | | | | |")
            continue
        lines.append(f"| {r['checkpoint']} | {r['size']}x{r['size']} | {r['frames_per_second']:.2f} | "
                     f"{r['render_ms_median']:.0f} | {100 * r['encode_share']:.1f} % | {r['mp4_kb']:.0f} | "
                     f"{r['decoded_frames']} of {r['frames']} |")
    srv = record.get("server")
    if srv:
        lines += ["", f"## Interactive renders beside a movie job (`{srv['scene']}`)", "",
                  f"`visnerf serve` with the bundled checkpoints; {srv['seconds_per_phase']:g} s idle, then as long "
                  f"while a job renders an orbit of {srv['job_frames']} frames at 256x256 (state at the end: "
                  f"{srv['job_state']}, {srv['job_frames_per_second']:.2f} frames/s over {srv['job_seconds']:.0f} s). "
                  f"Probe clients ask every {PROBE_PAUSE_S} s.", "",
                  "| request | idle p50 / p95 ms | beside the job p50 / p95 ms | p50 ratio | answered idle / beside |",
                  "| --- | --- | --- | --- | --- |"]
        for name, ask in PROBES.items():
            a, b = srv["probes"]["idle"][name], srv["probes"]["with_movie_job"][name]
            la, lb = a["latency_ms"], b["latency_ms"]
            ratio = lb["p50"] / la["p50"] if la["p50"] and lb["p50"] else float("nan")
            lines.append(f"| {ask.width}x{ask.height} {ask.quality} | {la['p50']:.0f} / {la['p95']:.0f} | "
                         f"{lb['p50']:.0f} / {lb['p95']:.0f} | {ratio:.2f} | {a['ok']} / {b['ok']} |")
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkpoints", nargs="+", type=Path,
                    default=[ROOT / "checkpoints" / "tangle_iso.safetensors", ROOT / "checkpoints" / "vortex_tf1.safetensors",
                             ROOT / "runs" / "nyx.safetensors"],
                    help="checkpoints (default: two bundled scenes and runs/nyx.safetensors from bench/nyx_train.py)")
    ap.add_argument("--sizes", default="256,512", help="square frame sizes, comma separated (default 256,512)")
    ap.add_argument("--frames", type=int, default=24, help="frames of the orbit (default 24)")
    ap.add_argument("--fps", type=float, default=24.0, help="frame rate written into the movie (default 24)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: the usable cores)")
    ap.add_argument("--server-scene", default="tangle_iso", help="bundled scene of the server phases (default tangle_iso)")
    ap.add_argument("--server-frames", type=int, default=48, help="frames of the server's movie job (default 48)")
    ap.add_argument("--server-seconds", type=float, default=20.0,
                    help="seconds of each server phase (default 20; 0 leaves the server out)")
    ap.add_argument("--out-dir", type=Path, default=RESULTS, help="results folder (default bench/results)")
    args = ap.parse_args(argv)
    try:
        sizes = [int(s) for s in args.sizes.split(",")]
    except ValueError:
        ap.error(f"--sizes must be comma-separated whole numbers, got {args.sizes!r}")
    if args.frames < 2 or any(s < 16 or s % 2 for s in sizes):
        ap.error("--frames must be at least 2 and every size even and at least 16")
    runtime.configure(args.threads)
    record = {"command": "python bench/movie_speed.py " + " ".join(argv if argv is not None else sys.argv[1:]),
              **machine_record(), "frames": args.frames, "rows": []}
    with tempfile.TemporaryDirectory(prefix="visnerf_movie_speed_") as tmp:
        for checkpoint in args.checkpoints:
            for size in sizes:
                if not checkpoint.is_file():
                    record["rows"].append({"checkpoint": str(checkpoint), "size": size, "error": "no such file"})
                    continue
                row = measure(checkpoint.resolve(), size, args.frames, args.fps, Path(tmp))
                print(f"{row['checkpoint']} {size}x{size}: {row['frames_per_second']:.2f} frames/s", file=sys.stderr)
                record["rows"].append(row)
        if args.server_seconds > 0:
            record["server"] = server_phases(args.server_scene, args.server_frames, args.server_seconds, Path(tmp))
    args.out_dir.mkdir(parents=True, exist_ok=True)
    (args.out_dir / "movie_speed.json").write_text(json.dumps(record, indent=2) + "\n")
    write_markdown(args.out_dir / "movie_speed.md", record)
    print(f"results -> {args.out_dir / 'movie_speed.md'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
