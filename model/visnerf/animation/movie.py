"""Movie files: H.264 MP4 (PyAV), GIF (Pillow) or a folder of numbered PNG frames.

A movie is written under a temporary name beside its destination and renamed when done. When the
frames stop early (Ctrl-C, or the frame iterator raises, e.g. ``RenderCancelled``), the file is
closed properly, so it holds a playable movie of the frames done, and is moved into place all the
same; with no frame done nothing is left behind.
"""

import math
import shutil
import signal
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Literal

import numpy as np
from PIL import Image

from visnerf.animation.interpolation import FrameSpec
from visnerf.inference import CancelCheck, SceneRenderer

MovieFormat = Literal["mp4", "gif", "png"]
MP4_CRF = 18
"""x264 constant rate factor: 18 is visually lossless for most content (lower: larger, better)."""
MIN_SIZE, MAX_SIZE = 16, 4096
MAX_FPS = 120.0


@dataclass(frozen=True)
class MovieSettings:
    """How to render and encode a movie."""

    fps: float = 30.0
    """Frames per second, in (0, 120]."""
    width: int = 512
    """Frame width in pixels, 16 to 4096 (even for mp4)."""
    height: int = 512
    """Frame height in pixels, 16 to 4096 (even for mp4)."""
    format: str = "mp4"
    """``mp4`` (H.264), ``gif`` or ``png`` (a folder of numbered PNG frames)."""
    quality: str = "full"
    """Render quality: ``full`` or ``preview`` (``SceneRenderer.render``)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.fps) and 0.0 < self.fps <= MAX_FPS):
            raise ValueError(f"fps must be in (0, {MAX_FPS:g}], got {self.fps}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if not MIN_SIZE <= value <= MAX_SIZE:
                raise ValueError(f"{name} must be in [{MIN_SIZE}, {MAX_SIZE}], got {value}")
        if self.format not in ("mp4", "gif", "png"):
            raise ValueError(f"format must be 'mp4', 'gif' or 'png', got {self.format!r}")
        if self.format == "mp4" and (self.width % 2 or self.height % 2):
            raise ValueError(f"an mp4 movie needs an even width and height (H.264 in yuv420p), "
                             f"got {self.width}x{self.height}")
        if self.quality not in ("full", "preview"):
            raise ValueError(f"quality must be 'full' or 'preview', got {self.quality!r}")


@dataclass
class MovieResult:
    """What ``write_movie`` wrote."""

    path: Path
    """The movie (file, or folder of PNGs); absent when no frame was written."""
    frames_written: int
    frames_total: int
    seconds: float
    """Wall-clock time of rendering and writing."""
    interrupted: bool
    """The frames stopped before ``frames_total`` (Ctrl-C or an error from the frame iterator)."""
    stopped_by: str = ""
    """What stopped them (``KeyboardInterrupt``, ``RenderCancelled: ...``); empty when not interrupted."""


def format_for_output(out: Path) -> str:
    """The movie format an output name asks for: ``.mp4``, ``.gif``, anything else a PNG folder."""
    return {".mp4": "mp4", ".gif": "gif"}.get(out.suffix.lower(), "png")


def render_frames(
    scene: SceneRenderer,
    frames: Sequence[FrameSpec],
    settings: MovieSettings,
    cancel: CancelCheck | None = None,
) -> Iterator[np.ndarray]:
    """Render each frame (uint8 [height, width, 3]) with ``scene.render``: full-quality frames use
    the per-setting occupancy grids and early ray termination it keeps. Raises ``RenderCancelled``
    once ``cancel`` answers True."""
    for frame in frames:
        yield scene.render(frame.c2w, frame.fov_deg, settings.width, settings.height, frame.params,
                           settings.quality, cancel, view_height=frame.view_height)


def write_movie(
    frames: Iterable[np.ndarray],
    out: Path,
    settings: MovieSettings,
    total: int,
    progress: Callable[[int, int], None] | None = None,
) -> MovieResult:
    """Write ``frames`` (uint8 [height, width, 3] each, ``total`` expected) to ``out``.

    Calls ``progress(frames_written, total)`` after each frame. An existing file at ``out`` is
    replaced; an existing folder (PNG output) must be empty. Frames of the wrong shape or dtype
    raise ValueError (nothing is left behind then).
    """
    out = Path(out)
    if settings.format == "png" and out.is_dir() and any(out.iterdir()):
        raise ValueError(f"{out} is a folder that is not empty: choose a new or empty one for the PNG frames")
    if settings.format != "png" and out.is_dir():
        raise ValueError(f"{out} is a folder: name a .{settings.format} file")
    tmp = out.with_name(f".{out.stem}.partial{out.suffix}")
    writer = _WRITERS[settings.format](tmp, settings)
    start = time.perf_counter()
    written, stopped_by = 0, ""
    iterator = iter(frames)
    try:
        while True:
            try:
                frame = next(iterator)
            except StopIteration:
                break
            except Exception as exc:  # the renderer stopped (RenderCancelled, ...): keep what is done
                stopped_by = f"{type(exc).__name__}: {exc}"
                break
            _check_frame(frame, settings)
            with _sigint_held() as held:  # a frame goes into the file whole, and is counted, or not at all
                writer.write(frame)
                written += 1
            if held:
                signal.raise_signal(signal.SIGINT)  # to the handler it was held from: KeyboardInterrupt
            if progress is not None:
                progress(written, total)
    except KeyboardInterrupt:
        stopped_by = "KeyboardInterrupt"
    except BaseException:
        writer.discard()
        raise
    with _sigint_held():  # a Ctrl-C now would leave a broken file: finishing takes a moment only
        if written == 0:
            writer.discard()
        else:
            writer.finish()
            _move_into_place(tmp, out)
    return MovieResult(out, written, total, time.perf_counter() - start, bool(stopped_by), stopped_by)


@contextmanager
def _sigint_held() -> Iterator[list[int]]:
    """Hold Ctrl-C (SIGINT) back during the block; the list it yields records any that came.
    Only the main thread receives signals: elsewhere (a server's worker) this does nothing."""
    caught: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield caught
        return
    previous = signal.signal(signal.SIGINT, lambda signum, _frame: caught.append(signum))
    try:
        yield caught
    finally:
        signal.signal(signal.SIGINT, previous)


def _check_frame(frame: object, settings: MovieSettings) -> None:
    expected = (settings.height, settings.width, 3)
    if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.shape != expected:
        got = f"{frame.dtype} {list(frame.shape)}" if isinstance(frame, np.ndarray) else type(frame).__name__
        raise ValueError(f"a movie frame must be uint8 {list(expected)} (height, width, rgb), got {got}")


def _move_into_place(tmp: Path, out: Path) -> None:
    if out.is_dir():  # an empty folder named as the PNG output
        out.rmdir()
    tmp.replace(out)


class _Mp4Writer:
    """H.264 (libx264, yuv420p, crf ``MP4_CRF``) in MP4, ``faststart`` so browsers can play it
    while it downloads."""

    def __init__(self, tmp: Path, settings: MovieSettings) -> None:
        import av

        self.tmp = tmp
        self.container = av.open(str(tmp), mode="w", format="mp4", options={"movflags": "+faststart"})
        rate = Fraction(settings.fps).limit_denominator(1001)
        self.stream = self.container.add_stream("libx264", rate=rate)
        self.stream.width, self.stream.height = settings.width, settings.height
        self.stream.pix_fmt = "yuv420p"
        self.stream.options = {"crf": str(MP4_CRF)}
        self.time_base = 1 / rate
        self.index = 0

    def write(self, frame: np.ndarray) -> None:
        import av

        video = av.VideoFrame.from_ndarray(frame, format="rgb24")
        video.pts, video.time_base = self.index, self.time_base
        self.index += 1
        for packet in self.stream.encode(video):
            self.container.mux(packet)

    def finish(self) -> None:
        for packet in self.stream.encode(None):  # flush the encoder's delayed frames
            self.container.mux(packet)
        self.container.close()

    def discard(self) -> None:
        try:
            self.container.close()
        finally:
            self.tmp.unlink(missing_ok=True)


class _GifWriter:
    """Pillow's GIF, one adaptive 256-colour palette per frame; frames are kept (one byte a pixel)
    until ``finish``, since GIF frames cannot be appended to a file. GIF counts time in hundredths
    of a second, so the frame time is 1/fps rounded to that. Pillow merges identical consecutive
    frames into one shown for their summed time."""

    def __init__(self, tmp: Path, settings: MovieSettings) -> None:
        self.tmp = tmp
        self.images: list[Image.Image] = []
        self.duration_ms = 10 * max(1, round(100.0 / settings.fps))

    def write(self, frame: np.ndarray) -> None:
        self.images.append(Image.fromarray(frame).quantize(256, method=Image.Quantize.MEDIANCUT))

    def finish(self) -> None:
        first, *rest = self.images
        first.save(self.tmp, format="GIF", save_all=True, append_images=rest, duration=self.duration_ms, loop=0)

    def discard(self) -> None:
        self.images.clear()
        self.tmp.unlink(missing_ok=True)


class _PngWriter:
    """A folder of ``frame_00000.png``, ``frame_00001.png``, ..."""

    def __init__(self, tmp: Path, settings: MovieSettings) -> None:
        self.tmp = tmp
        if tmp.exists():  # left by an earlier run that was killed
            shutil.rmtree(tmp)
        tmp.mkdir(parents=True)
        self.index = 0

    def write(self, frame: np.ndarray) -> None:
        Image.fromarray(frame).save(self.tmp / f"frame_{self.index:05d}.png")
        self.index += 1

    def finish(self) -> None:
        pass  # every frame is already a whole file

    def discard(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)


_WRITERS: dict[str, Callable[[Path, MovieSettings], "_Mp4Writer | _GifWriter | _PngWriter"]] = {
    "mp4": _Mp4Writer,
    "gif": _GifWriter,
    "png": _PngWriter,
}
