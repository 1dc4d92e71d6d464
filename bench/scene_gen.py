"""Time the generation of every synthetic scene and draw the contact sheet.

Generates each scene of ``visnerf scenes`` (the full protocol: 42 icosphere views per parameter
setting, 181 test views) at ``--res`` with the reference renderer, exactly as ``visnerf make-scene``
does, and records the seconds per scene to bench/results/scene_gen.json and .md. The requirement is
under five minutes per scene at 128x128 on the project's CPU machine. Then it draws a few training
and test views of every scene into docs/images/scenes_contact_sheet.png.

    python bench/scene_gen.py                      # all scenes at 128, temporary output
    python bench/scene_gen.py --scenes plume_time --res 256 --out-root /tmp/scenes --keep
    python bench/scene_gen.py --sheet-only --out-root /tmp/scenes   # redraw from kept datasets
"""

import argparse
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import torch
from bench_common import write_json

from visnerf.scenes.catalog import scene_catalog
from visnerf.scenes.contact_sheet import make_contact_sheet
from visnerf.scenes.writer import DatasetOptions, write_scene

ROOT = Path(__file__).resolve().parents[1]
LIMIT_S = 300.0


def machine() -> dict:
    return {
        "platform": f"{platform.machine()} {platform.system()}",
        "cpu_cores": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
    }


def write_markdown(path: Path, record: dict) -> None:
    m = record["machine"]
    lines = [
        "# Synthetic scene generation time",
        "",
        f"`python bench/scene_gen.py --res {record['resolution']} --workers {record['workers']}` on "
        f"{m['platform']}, {m['cpu_cores']} CPU cores, no GPU, torch {m['torch']}, {record['workers']} "
        f"render process(es) with one torch thread each, {record['date']}.",
        "",
        f"Every scene with the full protocol ({record['views']} training views per parameter setting, "
        f"{record['test_views']} test views), {record['resolution']}x{record['resolution']}, PNG writing "
        f"included. Requirement: under {LIMIT_S:.0f} s per scene.",
        "",
        "| scene | kind | K | settings | images | seconds | ms per image | under 5 min | load avg (1 min) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for s in record["scenes"]:
        lines.append(
            f"| {s['name']} | {s['kind']} | {s['K']} | {s['settings']} | {s['images']} | "
            f"{s['seconds']:.1f} | {1000 * s['seconds_per_image']:.0f} | "
            f"{'yes' if s['under_limit'] else 'NO'} | {s['load_before']:.1f} -> {s['load_after']:.1f} |"
        )
    lines += [
        "",
        f"Total: {record['total_seconds']:.1f} s for {sum(s['images'] for s in record['scenes'])} images.",
        "",
        "Notes:",
        "",
        "- The machine is shared with other jobs; the 1-minute load average before and after each scene "
        "is recorded because it moves these figures (it includes this benchmark's own render processes, "
        "so a load equal to the number of workers means an otherwise idle machine). Parallelism is by "
        "processes (`visnerf make-scene --workers`), each with one torch thread: with two torch threads "
        "on a busy 2-core machine the small vectorised passes of the reference renderer run many times "
        "slower.",
        "- Contact sheet of a few training and test views per scene: docs/images/scenes_contact_sheet.png.",
    ]
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    catalog = scene_catalog()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--res", type=int, default=128, help="image size (default 128)")
    parser.add_argument("--scenes", nargs="+", default=list(catalog), choices=list(catalog), metavar="NAME")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--workers", type=int, default=2, help="render processes (default 2: both cores)")
    parser.add_argument("--out-root", type=Path, help="where the datasets go (default: a temporary folder)")
    parser.add_argument("--keep", action="store_true", help="keep the datasets (with --out-root)")
    parser.add_argument("--results", type=Path, default=ROOT / "bench" / "results", help="results folder")
    parser.add_argument(
        "--sheet",
        type=Path,
        help="contact sheet PNG (default for a full run: docs/images/scenes_contact_sheet.png)",
    )
    parser.add_argument("--sheet-only", action="store_true", help="only redraw the sheet from --out-root")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    full_run = args.res == 128 and args.scenes == list(catalog)
    sheet = args.sheet or (ROOT / "docs" / "images" / "scenes_contact_sheet.png" if full_run else None)
    root = args.out_root or Path(tempfile.mkdtemp(prefix="visnerf_scene_gen_"))
    datasets = [root / name for name in args.scenes]
    if args.sheet_only:
        make_contact_sheet(datasets, sheet or ROOT / "docs" / "images" / "scenes_contact_sheet.png")
        return 0
    options = DatasetOptions(resolution=args.res)
    record = {
        "resolution": args.res,
        "views": options.n_views,
        "test_views": options.n_test_views,
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        "machine": machine(),
        "workers": args.workers,
        "limit_seconds": LIMIT_S,
        "scenes": [],
    }
    started = time.perf_counter()
    for name, out_dir in zip(args.scenes, datasets, strict=True):
        spec = catalog[name]
        if out_dir.exists():
            shutil.rmtree(out_dir)
        load_before = os.getloadavg()[0]
        summary = write_scene(spec, out_dir, options, progress=True, workers=args.workers)
        images = summary.n_train + summary.n_test
        entry = {
            "name": name,
            "kind": spec.kind,
            "K": len(spec.axes),
            "settings": summary.n_train // options.n_views,
            "images": images,
            "seconds": round(summary.seconds, 2),
            "seconds_per_image": round(summary.seconds / images, 4),
            "under_limit": summary.seconds < LIMIT_S,
            "load_before": round(load_before, 2),
            "load_after": round(os.getloadavg()[0], 2),
        }
        record["scenes"].append(entry)
        print(f"{name}: {images} images in {summary.seconds:.1f} s", file=sys.stderr)
    record["total_seconds"] = round(time.perf_counter() - started, 1)
    args.results.mkdir(parents=True, exist_ok=True)
    stem = "scene_gen" if full_run else "scene_gen.partial"  # a partial run never replaces the record
    write_json(args.results / f"{stem}.json", record)
    write_markdown(args.results / f"{stem}.md", record)
    print(f"results -> {args.results / stem}.json and .md", file=sys.stderr)
    if sheet is not None:
        make_contact_sheet(datasets, sheet)
        print(f"contact sheet -> {sheet}", file=sys.stderr)
    if args.out_root is None or not args.keep:
        for out_dir in datasets:
            shutil.rmtree(out_dir, ignore_errors=True)
        if args.out_root is None:
            shutil.rmtree(root, ignore_errors=True)
    return 0 if all(s["under_limit"] for s in record["scenes"]) else 1


if __name__ == "__main__":
    sys.exit(main())
