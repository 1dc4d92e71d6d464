"""A synthetic scene as a Blender dataset and as Cinema databases in each producer's convention,
trained side by side with no flags, scored on the same held-out views.

    python bench/cinema_formats.py --scene tangle_static --res 100 --views 90 --minutes 5 \
        --formats pycinema --out bench/results/cinema_formats

Each format: ``visnerf make-scene`` (``--format cinema --convention C`` for a database), then
``visnerf train`` on both threads for ``--minutes`` with every ninth view held out, then the
held-out frames rendered at full quality against their ground truth. Writes
``cinema_formats.json`` and ``.md``.
"""

import visnerf  # noqa: F401  (before torch: it sets the OpenMP wait policy that torch reads once)

# isort: split
import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_common import load_average, machine_record, markdown_header, render_frame, write_results

from visnerf.config import HoldoutConfig
from visnerf.data.datasets import load_dataset
from visnerf.data.holdout import split_holdout
from visnerf.evaluation.metrics import psnr
from visnerf.inference import load_scene

FORMATS = ("blender", "pycinema", "paraview", "ascent")


def _run(args: list[str]) -> None:
    subprocess.run([sys.executable, "-m", "visnerf.cli", *args], check=True)


def measure(fmt: str, opts: argparse.Namespace, work: Path) -> dict:
    root = work / fmt
    extra = [] if fmt == "blender" else ["--format", "cinema", "--convention", fmt]
    _run(["make-scene", opts.scene, "--out", str(root), "--res", str(opts.res), "--views", str(opts.views),
          "--test-views", "2", "--quiet", *extra])
    data = root if fmt == "blender" else root / "train.cdb"
    held = tuple(range(0, opts.views, 9))
    ckpt = work / f"{fmt}.safetensors"
    started = time.perf_counter()
    _run(["train", str(data), "--out", str(ckpt), "--time-budget", str(opts.minutes), "--quiet",
          "--holdout-views", ",".join(map(str, held))])
    seconds = time.perf_counter() - started
    _, val = split_holdout(load_dataset(data), HoldoutConfig(views=held))
    assert val is not None
    scene = load_scene(ckpt)
    scores = [psnr(*render_frame(scene, val, i, opts.res, opts.res)) for i in range(val.n_frames)]
    return {"format": fmt, "held_out_frames": val.n_frames, "held_out_psnr": float(np.mean(scores)),
            "orthographic": val.intrinsics.orthographic, "wall_seconds": round(seconds, 1),
            "iterations": scene.info.training.get("iterations")}


def write_markdown(path: Path, record: dict) -> None:
    lines = markdown_header("A scene in the Blender format and as Cinema databases", record)
    lines += ["", "| format | camera | held-out frames | held-out PSNR (dB) | steps |", "| --- | --- | --- | --- | --- |"]
    for row in record["rows"]:
        camera = "orthographic" if row["orthographic"] else "perspective"
        lines.append(f"| {row['format']} | {camera} | {row['held_out_frames']} | {row['held_out_psnr']:.2f} | "
                     f"{row['iterations']} |")
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="tangle_static")
    ap.add_argument("--res", type=int, default=100)
    ap.add_argument("--views", type=int, default=90)
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--formats", default=",".join(FORMATS))
    ap.add_argument("--out", type=Path, default=Path("bench/results/cinema_formats"))
    opts = ap.parse_args()
    record = {**machine_record(), "command": "python " + " ".join(sys.argv), "rows": []}
    load = {"before": load_average()}
    with tempfile.TemporaryDirectory() as work:
        for fmt in opts.formats.split(","):
            record["rows"].append(measure(fmt, opts, Path(work)))
            print(record["rows"][-1], file=sys.stderr)
    load["after"] = load_average()
    record["load_average_1min"] = load
    write_results(opts.out, "cinema_formats", record, write_markdown)


if __name__ == "__main__":
    main()
