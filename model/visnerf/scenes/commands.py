"""``visnerf make-scene`` and ``visnerf scenes``: generate and list the synthetic datasets."""

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from visnerf.data.parsers.cinema_cameras import CONVENTIONS
from visnerf.scenes.catalog import SceneSpec, get_scene, scene_catalog
from visnerf.scenes.cinema_writer import write_cinema_scene
from visnerf.scenes.writer import DatasetOptions, output_dir_problem, write_scene


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``make-scene`` and ``scenes`` sub-commands."""
    make = subparsers.add_parser(
        "make-scene",
        help="render a synthetic dataset (ground truth) from an analytic volume",
        description="Render a synthetic scene with the reference volume renderer and write it as a "
        "dataset: 42 icosphere views per parameter setting for training, a 181-view path for testing.",
    )
    make.add_argument("name", help="scene name (see `visnerf scenes`)")
    make.add_argument("--out", type=Path, required=True, help="output directory")
    make.add_argument("--res", type=int, default=None, help="image width and height in pixels (default: the "
                      "scene's, 128 for most, 800 for the shells; `visnerf scenes`)")
    make.add_argument(
        "--views", type=int, default=None, help="training views per parameter setting (default: the scene's, "
        "42 for most; `visnerf scenes`)"
    )
    make.add_argument("--test-views", type=int, default=181, help="views on the test path (default 181)")
    make.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    make.add_argument("--workers", type=int, default=1, help="render in this many processes (default 1)")
    make.add_argument("--format", choices=("blender", "cinema"), default="blender",
                      help="blender: transforms_*.json (default); cinema: DIR/train.cdb and DIR/test.cdb databases")
    make.add_argument("--convention", choices=CONVENTIONS, default="pycinema",
                      help="the producer a Cinema database is written like: pycinema (orthographic .h5), "
                           "paraview or ascent (phi/theta PNG); default pycinema")
    make.add_argument("--force", action="store_true", help="overwrite a non-empty output directory")
    make.add_argument("--quiet", action="store_true", help="no progress bar")
    make.set_defaults(func=make_scene_command)

    listing = subparsers.add_parser("scenes", help="list the synthetic scenes and their parameters")
    listing.add_argument("--json", action="store_true", help="print the list as JSON")
    listing.set_defaults(func=list_scenes_command)


def _fail(message: str) -> int:
    print(f"visnerf make-scene: error: {message}", file=sys.stderr)
    return 2


def make_scene_command(args: argparse.Namespace) -> int:
    """Validate everything before writing anything; exit code 2 on bad input."""
    try:
        spec = get_scene(args.name)
    except KeyError as exc:
        return _fail(str(exc.args[0]))
    if args.res is None:
        args.res = spec.resolution
    if args.res < 8:
        return _fail(f"--res must be at least 8, got {args.res}")
    views = spec.n_views if args.views is None else args.views
    if views < 1:
        return _fail(f"--views must be at least 1, got {views}")
    if args.test_views < 2:
        return _fail(f"--test-views must be at least 2, got {args.test_views}")
    if args.threads < 1 or args.workers < 1:
        return _fail(f"--threads and --workers must be at least 1, got {args.threads} and {args.workers}")
    problem = output_dir_problem(args.out, args.force)
    if problem is not None:
        return _fail(problem)
    torch.set_num_threads(args.threads)
    options = DatasetOptions(resolution=args.res, n_views=views, n_test_views=args.test_views)
    if args.format == "cinema":
        started = time.perf_counter()
        count = write_cinema_scene(spec, args.out, options, args.convention)
        print(f"{spec.name}: {count} images ({args.res}x{args.res}, {args.convention}) in "
              f"{time.perf_counter() - started:.1f} s -> {args.out}/train.cdb, {args.out}/test.cdb")
        return 0
    summary = write_scene(spec, args.out, options, progress=not args.quiet, workers=args.workers)
    print(
        f"{spec.name}: {summary.n_train} training and {summary.n_test} test images "
        f"({args.res}x{args.res}) in {summary.seconds:.1f} s -> {args.out}"
    )
    return 0


def describe_scene(spec: SceneSpec) -> dict:
    """A JSON-ready description of a scene and its parameters."""
    return {
        "name": spec.name,
        "title": spec.title,
        "kind": spec.kind,
        "description": spec.description,
        "params": [
            {"name": a.name, "min": a.low, "max": a.high, "count": a.count, "description": a.description}
            for a in spec.axes
        ],
        "fixed": dict(spec.fixed),
        "views_per_setting": spec.n_views,
        "resolution": spec.resolution,
        "rgba": spec.rgba,
    }


def list_scenes_command(args: argparse.Namespace) -> int:
    """Print the scenes, one per line with their parameters (or JSON with ``--json``)."""
    scenes = [describe_scene(spec) for spec in scene_catalog().values()]
    if args.json:
        print(json.dumps(scenes, indent=2))
        return 0
    width = max(len(s["name"]) for s in scenes)
    for scene in scenes:
        params = ", ".join(f"{p['name']} [{p['min']:g}, {p['max']:g}] x{p['count']}" for p in scene["params"])
        if not params:
            params = "static: " + ", ".join(f"{k}={v:g}" for k, v in scene["fixed"].items())
        print(f"{scene['name']:<{width}}  {scene['kind']:<3}  K={len(scene['params'])}  {params}  "
              f"({scene['views_per_setting']} views, {scene['resolution']} px{', RGBA' if scene['rgba'] else ''})")
        print(f"{'':<{width}}  {scene['title']}: {scene['description']}")
    return 0
