"""Render memory: the peak resident memory of one large full-quality frame, in blocks of rows
(``renderer.BLOCK_RAYS``, the product) against the whole frame as one block (as before blocks).

Each measurement runs in a fresh process: load the checkpoint, render one untimed 64x64 frame,
read the peak resident set (``ru_maxrss``), render the large frame at the scene's default camera
and parameters, read the peak again. Reports the peak's rise over the loaded model (median over
rounds, each round running the two ways in turn, every other round in reverse order), the render
time and whether the two ways gave the same 8-bit frame. Writes render_memory.json and
render_memory.md to --out-dir (bench/results).

    .venv/bin/python bench/render_memory.py --threads 2
    .venv/bin/python bench/render_memory.py --checkpoints checkpoints/cosmo_sim.safetensors --size 2048
"""

import argparse
import hashlib
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from bench_common import load_average, machine_record, write_results

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
WAYS = ("blocks", "whole frame")


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def measure_one(checkpoint: Path, size: int, way: str, threads: int | None) -> dict[str, Any]:
    """One measurement, in this (fresh) process."""
    from visnerf import runtime
    from visnerf.data.cameras import orbit_c2w
    from visnerf.inference import load_scene
    from visnerf.rendering import renderer

    runtime.configure(threads)
    scene = load_scene(checkpoint)
    camera = scene.info.camera
    c2w = orbit_c2w(camera["azimuth"], camera["elevation"], camera["distance"])
    scene.render(c2w, camera["fov_deg"], 64, 64)
    loaded = peak_mb()
    if way == "whole frame":
        renderer.BLOCK_RAYS = size * size  # one block
    start = time.perf_counter()
    frame = scene.render(c2w, camera["fov_deg"], size, size)
    seconds = time.perf_counter() - start
    return {"loaded_mb": loaded, "peak_mb": peak_mb(), "seconds": seconds,
            "frame_sha256": hashlib.sha256(frame.tobytes()).hexdigest()}


def run_one(checkpoint: Path, size: int, way: str, threads: int | None) -> dict[str, Any]:
    command = [sys.executable, __file__, "--measure", str(checkpoint), str(size), way]
    if threads is not None:
        command += ["--threads", str(threads)]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}"}
    return json.loads(done.stdout.strip().splitlines()[-1])


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in runs if "error" not in r]
    if not ok:
        return {"error": runs[0]["error"] if runs else "no runs"}
    return {
        "rise_mb": statistics.median(r["peak_mb"] - r["loaded_mb"] for r in ok),
        "loaded_mb": statistics.median(r["loaded_mb"] for r in ok),
        "seconds": statistics.median(r["seconds"] for r in ok),
        "frames": sorted({r["frame_sha256"] for r in ok}),
        "runs": runs,
    }


def write_markdown(path: Path, record: dict[str, Any]) -> None:
    load = record["load_average_1min"]
    lines = [
        "# Render memory: a large frame in blocks of rows against the whole frame at once",
        "",
        f"Command: `{record['command']}`  ",
        f"Machine: {record['machine']}, torch {record['torch']}, {record['threads']} render thread(s), "
        f"{record['date']}; 1-min load average {load['before']} before, {load['after']} after.",
        "",
        f"One {record['size']}x{record['size']} full-quality frame per fresh process, at the scene's default camera "
        f"and parameters; {record['rounds']} round(s), the two ways in turn. \"Rise\": the peak resident memory "
        "during the frame over the peak after loading the model and one 64x64 frame (median). \"Blocks\": "
        f"the product, {record['block_rays']} rays a block (`renderer.BLOCK_RAYS`); \"whole frame\": all rays "
        "in one block, as the renderer did before blocks.",
        "",
        "| checkpoint | loaded (MB) | rise, blocks (MB) | rise, whole frame (MB) | ratio | seconds, blocks / whole frame "
        "| same 8-bit frame |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in record["rows"]:
        b, w = row["blocks"], row["whole frame"]
        if "error" in b or "error" in w:
            lines.append(f"| {row['name']} | error: {b.get('error') or w.get('error')} | | | | | |")
            continue
        same = "yes" if len(b["frames"]) == 1 and b["frames"] == w["frames"] else "**no**"
        lines.append(f"| {row['name']} | {b['loaded_mb']:.0f} | {b['rise_mb']:.0f} | {w['rise_mb']:.0f} | "
                     f"{w['rise_mb'] / max(b['rise_mb'], 1.0):.2f} | {b['seconds']:.2f} / {w['seconds']:.2f} | {same} |")
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkpoints", nargs="+", type=Path,
                    default=sorted((ROOT / "checkpoints").glob("*.safetensors")),
                    help="checkpoints (default: the bundled ones)")
    ap.add_argument("--size", type=int, default=1440,
                    help="side of the square frame (default 1440, the largest full frame the server allows)")
    ap.add_argument("--rounds", type=int, default=2, help="rounds of both ways (default 2)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: the usable cores)")
    ap.add_argument("--out-dir", type=Path, default=RESULTS, help="results folder (default bench/results)")
    ap.add_argument("--measure", nargs=3, metavar=("CHECKPOINT", "SIZE", "WAY"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.measure:
        checkpoint, size, way = args.measure
        print(json.dumps(measure_one(Path(checkpoint), int(size), way, args.threads)))
        return 0
    if args.size < 16 or args.rounds < 1:
        ap.error("--size must be at least 16 and --rounds at least 1")
    missing = [str(c) for c in args.checkpoints if not c.is_file()]
    if missing:
        ap.error(f"no such checkpoint: {', '.join(missing)}")
    from visnerf import runtime
    from visnerf.rendering.renderer import BLOCK_RAYS

    runtime.configure(args.threads)
    record: dict[str, Any] = {
        "command": "python bench/render_memory.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        **machine_record(), "threads": runtime.default_threads() if args.threads is None else args.threads,
        "size": args.size, "rounds": args.rounds, "block_rays": BLOCK_RAYS, "rows": [],
        "load_average_1min": {"before": load_average()},
    }
    for checkpoint in args.checkpoints:
        runs: dict[str, list[dict[str, Any]]] = {way: [] for way in WAYS}
        for r in range(args.rounds):
            for way in (WAYS if r % 2 == 0 else WAYS[::-1]):
                runs[way].append(run_one(checkpoint, args.size, way, args.threads))
                print(f"{checkpoint.stem} {way}: {runs[way][-1]}", file=sys.stderr)
        record["rows"].append({"name": checkpoint.stem, "checkpoint": str(checkpoint),
                               **{way: summarise(runs[way]) for way in WAYS}})
    record["load_average_1min"]["after"] = load_average()
    write_results(args.out_dir, "render_memory", record, write_markdown)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
