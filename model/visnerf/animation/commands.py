"""Sub-command ``animate``: render a movie of a checkpoint along a camera and parameter path.

    visnerf animate scene.safetensors --orbit 120 --fps 30 --size 512x512 -o turn.mp4
    visnerf animate scene.safetensors --path path.json -o frames/        (a folder of PNGs)

Every input is checked before anything is rendered: a bad one prints ``error: ...`` and exits 2
with nothing written. Ctrl-C keeps a playable movie of the frames done and exits 130.
"""

import argparse
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from visnerf.arg_types import add_device_option, whole_number_at_least
from visnerf.arg_types import number as parse_number
from visnerf.config import FramesConfig
from visnerf.config_options import add_config_options, frames_config

if TYPE_CHECKING:
    from visnerf.animation.movie import MovieSettings
    from visnerf.animation.path import AnimationPath, FrameSpec
    from visnerf.inference import SceneRenderer

DEFAULT_SWEEP_FRAMES = 90
DEFAULT_TEST_VIEWS = 181
"""As ``visnerf make-scene --test-views``."""


class _InputError(Exception):
    """A bad command-line input; the message follows ``error:``."""


def _animate(args: argparse.Namespace) -> int:
    from visnerf.animation.keys import PathError
    from visnerf.animation.movie import MovieSettings, format_for_output
    from visnerf.checkpoint import CheckpointError

    out = Path(args.output)
    try:
        width, height = _size(args.size)
        settings = MovieSettings(fps=args.fps, width=width, height=height, format=format_for_output(out),
                                 quality=args.quality)
        if not out.absolute().parent.is_dir():
            raise _InputError(f"the folder {out.absolute().parent} does not exist")
        if settings.format == "png" and out.exists() and not (out.is_dir() and not any(out.iterdir())):
            raise _InputError(f"{out} exists: the PNG frames need a new or empty folder (or name a .mp4 or .gif)")
        if settings.format != "png" and out.is_dir():
            raise _InputError(f"{out} is a folder: name a .{settings.format} file")
        if args.param and (args.path or args.test_path is not None):
            raise _InputError("--param sets the values of --orbit and --sweep; a --path file and --test-path "
                              "set their own")
        path_doc = _read_path_file(Path(args.path)) if args.path else None
        from visnerf.inference import load_scene
        from visnerf.runtime import pick_device

        scene = load_scene(args.checkpoint, pick_device(args.device), frames_config(args))
        path = _build_path(args, scene, path_doc)
        from visnerf.animation.path import sample_frames

        frames = sample_frames(path, settings.fps, scene.info.params)
    except (_InputError, PathError, CheckpointError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return _write(scene, frames, settings, out, quiet=args.quiet)


def _write(scene: "SceneRenderer", frames: "list[FrameSpec]", settings: "MovieSettings", out: Path, quiet: bool) -> int:
    from tqdm import tqdm

    from visnerf.animation.movie import render_frames, write_movie

    total = len(frames)
    print(f"rendering {total} frames, {settings.width}x{settings.height} at {settings.fps:g} fps "
          f"({total / settings.fps:.1f} s) into {out}", file=sys.stderr)
    with tqdm(total=total, unit="frame", desc="animate", disable=quiet, file=sys.stderr) as bar:
        result = write_movie(render_frames(scene, frames, settings), out, settings, total,
                             lambda done, _: bar.update(done - bar.n))
    if not result.interrupted:
        print(f"wrote {out} ({total} frames in {result.seconds:.1f} s)")
        return 0
    kept = (f"{out} holds a playable movie of the {result.frames_written} frames done"
            if result.frames_written else "nothing was written")
    if result.stopped_by == "KeyboardInterrupt":
        print(f"interrupted after {result.frames_written} of {total} frames: {kept}", file=sys.stderr)
        return 130
    print(f"error: rendering stopped after {result.frames_written} of {total} frames ({result.stopped_by}): {kept}",
          file=sys.stderr)
    return 1


def _size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise _InputError(f"--size must be WxH (e.g. 512x512), got {text!r}") from None
    return width, height


def _read_path_file(path: Path) -> object:
    try:
        text = path.read_text()
    except OSError as exc:
        raise _InputError(f"cannot read the path file {path}: {exc.strerror or exc}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise _InputError(f"{path} is not valid JSON: {exc}") from None
    except RecursionError:
        raise _InputError(f"{path} is nested too deeply to be a path") from None


def _params(items: list[str], scene: "SceneRenderer") -> dict[str, float]:
    """``--param NAME=VALUE`` values, checked against the scene's axes."""
    from visnerf.animation.parse import clamp_to_axis

    axes = {a.name: a for a in scene.info.params}
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        number = parse_number(value) if sep else math.nan
        if not math.isfinite(number):
            raise _InputError(f"--param {item!r} must be NAME=NUMBER")
        if name not in axes:
            raise _InputError(f"--param {name}: unknown parameter; this scene has {sorted(axes)}")
        out[name] = clamp_to_axis(number, axes[name], f"--param {name}")
    return out


def _build_path(args: argparse.Namespace, scene: "SceneRenderer", path_doc: object) -> "AnimationPath":
    from visnerf.animation.path import CameraKey, orbit_path, parse_path, sweep_path, test_path
    from visnerf.lens import choose_lens

    cam = scene.info.camera
    try:
        fov, view_height = choose_lens(cam, args.fov, args.view_height)
    except ValueError as exc:
        raise _InputError(f"--fov, --view-height: {exc}") from None
    distance = float(args.distance if args.distance is not None else cam.get("distance", 2.0))
    elevation = float(args.elevation if args.elevation is not None else cam.get("elevation", 0.0))
    azimuth = float(args.azimuth if args.azimuth is not None else cam.get("azimuth", 0.0))
    axes = scene.info.params
    if path_doc is not None:
        return parse_path(path_doc, axes, cam)
    if args.test_path is not None:
        return test_path(args.test_path, axes, distance, fov, fps=float(args.fps), view_height=view_height)
    params = _params(args.param, scene)
    camera = CameraKey(azimuth, elevation, distance, fov, view_height)  # names a bad --elevation, --fov...
    if args.orbit is not None:
        return orbit_path(args.orbit, float(args.fps), elevation, distance, fov, params, start_azimuth=azimuth,
                          view_height=view_height)
    return sweep_path(args.sweep, args.frames, float(args.fps), axes, camera, params)


def _fps(text: str) -> float:
    value = parse_number(text)
    if not (math.isfinite(value) and 0.0 < value <= 120.0):
        raise argparse.ArgumentTypeError(f"expected frames per second in (0, 120], got {text!r}")
    return value


def register(sub: argparse._SubParsersAction) -> None:
    a = sub.add_parser("animate", help="render a movie along a camera and parameter path",
                       description="Render a movie of a checkpoint: along a keyframed path (JSON, see "
                                   "visnerf.animation.keys), a turn around the scene, a sweep of one "
                                   "parameter or the evaluation protocol's test path.")
    a.add_argument("checkpoint")
    what = a.add_mutually_exclusive_group(required=True)
    what.add_argument("--path", default=None, metavar="PATH.json", help="keyframed path document (version 1)")
    what.add_argument("--orbit", type=whole_number_at_least(1), default=None, metavar="N",
                      help="one turn in azimuth in N frames (the last does not repeat the first)")
    what.add_argument("--sweep", default=None, metavar="AXIS", help="sweep one parameter from its min to its max")
    what.add_argument("--test-path", type=whole_number_at_least(2), nargs="?", const=DEFAULT_TEST_VIEWS, default=None,
                      metavar="N",
                      help=f"the evaluation protocol's test path in N views (default {DEFAULT_TEST_VIEWS})")
    a.add_argument("--frames", type=whole_number_at_least(2), default=DEFAULT_SWEEP_FRAMES,
                   help=f"frames of a --sweep (default {DEFAULT_SWEEP_FRAMES})")
    a.add_argument("--fps", type=_fps, default=30.0, help="frames per second (default 30)")
    a.add_argument("--size", default="512x512", metavar="WxH", help="frame size (even for .mp4; default 512x512)")
    a.add_argument("--quality", choices=("full", "preview"), default="full")
    a.add_argument("--azimuth", type=float, default=None, help="start azimuth of --orbit, azimuth of --sweep "
                                                               "(default: the scene's camera)")
    a.add_argument("--elevation", type=float, default=None, help="elevation of --orbit and --sweep")
    a.add_argument("--distance", type=float, default=None, help="camera distance of --orbit, --sweep, --test-path")
    lens = a.add_mutually_exclusive_group()
    lens.add_argument("--fov", type=float, default=None,
                      help="horizontal field of view in degrees: a perspective movie (default: the scene's lens)")
    lens.add_argument("--view-height", type=float, default=None, metavar="H",
                      help="world units the frame spans vertically: an orthographic movie")
    a.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="a parameter value held during --orbit and --sweep (default: the axis default)")
    add_device_option(a)
    a.add_argument("--quiet", action="store_true", help="no progress bar")
    a.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="movie.mp4 (H.264), movie.gif, or any other name: a folder of numbered PNG frames")
    add_config_options(a, (FramesConfig,))
    a.set_defaults(func=_animate)


__all__ = ["register"]
