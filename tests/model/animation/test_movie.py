"""Movie files read back with PyAV and Pillow: frame count, size, rate, content; stopping early."""

from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pytest
from PIL import Image

from visnerf.animation.movie import MovieSettings, format_for_output, write_movie
from visnerf.inference import RenderCancelled

W, H = 48, 32


def ramp_frames(n: int) -> list[np.ndarray]:
    """Frame i: a horizontal ramp plus 20 i, so frames differ from each other and within themselves."""
    ramp = np.linspace(0, 80, W, dtype=np.float64)[None, :, None]  # [1, w, 1]
    return [np.broadcast_to(ramp + 20 * i, (H, W, 3)).astype(np.uint8) for i in range(n)]


def decode_mp4(path: Path) -> tuple[list[np.ndarray], Fraction]:
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
        return frames, stream.average_rate


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse)


def only_file(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def test_an_mp4_reads_back_with_its_frames_size_and_rate(tmp_path: Path) -> None:
    frames = ramp_frames(8)
    calls: list[tuple[int, int]] = []
    out = tmp_path / "m.mp4"
    result = write_movie(iter(frames), out, MovieSettings(fps=24.0, width=W, height=H), 8,
                         lambda done, total: calls.append((done, total)))
    assert (result.frames_written, result.frames_total, result.interrupted) == (8, 8, False)
    assert calls == [(i, 8) for i in range(1, 9)]
    decoded, rate = decode_mp4(out)
    assert rate == 24 and len(decoded) == 8 and decoded[0].shape == (H, W, 3)
    for got, sent in zip(decoded, frames, strict=True):
        assert psnr(got, sent) > 35.0
    assert only_file(tmp_path) == ["m.mp4"]  # the temporary name is gone


def test_a_fractional_frame_rate_is_kept(tmp_path: Path) -> None:
    write_movie(iter(ramp_frames(3)), tmp_path / "m.mp4", MovieSettings(fps=30000 / 1001, width=W, height=H), 3)
    assert decode_mp4(tmp_path / "m.mp4")[1] == Fraction(30000, 1001)


def stop_after(frames: list[np.ndarray], n: int, error: BaseException):
    for i, frame in enumerate(frames):
        if i == n:
            raise error
        yield frame


@pytest.mark.parametrize("error", [KeyboardInterrupt(), RenderCancelled("render cancelled")])
def test_stopping_after_five_frames_leaves_a_playable_movie_of_five(tmp_path: Path, error: BaseException) -> None:
    frames = ramp_frames(10)
    out = tmp_path / "m.mp4"
    result = write_movie(stop_after(frames, 5, error), out, MovieSettings(fps=10.0, width=W, height=H), 10)
    assert result.interrupted and (result.frames_written, result.frames_total) == (5, 10)
    assert result.stopped_by.startswith(type(error).__name__)
    decoded, _ = decode_mp4(out)
    assert len(decoded) == 5 and psnr(decoded[4], frames[4]) > 35.0
    assert only_file(tmp_path) == ["m.mp4"]


@pytest.mark.parametrize("fmt, name", [("mp4", "m.mp4"), ("gif", "m.gif"), ("png", "frames")])
def test_no_frame_done_leaves_nothing(tmp_path: Path, fmt: str, name: str) -> None:
    result = write_movie(stop_after(ramp_frames(3), 0, KeyboardInterrupt()), tmp_path / name,
                         MovieSettings(width=W, height=H, format=fmt), 3)
    assert result.interrupted and result.frames_written == 0
    assert only_file(tmp_path) == []


def test_a_wrong_frame_raises_and_leaves_nothing(tmp_path: Path) -> None:
    frames = [*ramp_frames(2), np.zeros((H, W, 4), np.uint8)]
    with pytest.raises(ValueError, match=r"a movie frame must be uint8 \[32, 48, 3\].*got uint8 \[32, 48, 4\]"):
        write_movie(iter(frames), tmp_path / "m.mp4", MovieSettings(width=W, height=H), 3)
    assert only_file(tmp_path) == []


def test_a_gif_reads_back_with_its_frames(tmp_path: Path) -> None:
    frames = ramp_frames(6)
    result = write_movie(iter(frames), tmp_path / "m.gif", MovieSettings(fps=20.0, width=W, height=H, format="gif"), 6)
    assert result.frames_written == 6
    with Image.open(tmp_path / "m.gif") as gif:
        assert gif.n_frames == 6 and gif.size == (W, H)
        assert gif.info["duration"] == 50  # 1 / 20 s
        for i, sent in enumerate(frames):
            gif.seek(i)
            assert psnr(np.asarray(gif.convert("RGB")), sent) > 35.0


def test_a_png_folder_holds_the_exact_frames(tmp_path: Path) -> None:
    frames = ramp_frames(4)
    out = tmp_path / "frames"
    out.mkdir()  # an empty folder may be named
    write_movie(iter(frames), out, MovieSettings(width=W, height=H, format="png"), 4)
    assert only_file(out) == [f"frame_{i:05d}.png" for i in range(4)]
    for i, sent in enumerate(frames):
        np.testing.assert_array_equal(np.asarray(Image.open(out / f"frame_{i:05d}.png")), sent)
    assert only_file(tmp_path) == ["frames"]


def test_a_folder_that_is_not_empty_is_refused(tmp_path: Path) -> None:
    (tmp_path / "keep.txt").write_text("mine")
    with pytest.raises(ValueError, match="not empty"):
        write_movie(iter(ramp_frames(1)), tmp_path, MovieSettings(width=W, height=H, format="png"), 1)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"width": 33}, "mp4 movie needs an even width and height"),
        ({"height": 8}, r"height must be in \[16, 4096\]"),
        ({"width": 5000, "format": "png"}, r"width must be in \[16, 4096\]"),
        ({"fps": 0.0}, r"fps must be in \(0, 120\]"),
        ({"fps": 121.0}, r"fps must be in \(0, 120\]"),
        ({"format": "avi"}, "format must be"),
        ({"quality": "best"}, "quality must be"),
    ],
)
def test_settings_are_checked(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        MovieSettings(**kwargs)


def test_odd_sizes_are_fine_for_gif_and_png() -> None:
    assert MovieSettings(width=33, height=17, format="gif").width == 33
    assert MovieSettings(width=33, height=17, format="png").height == 17


def test_the_output_name_picks_the_format() -> None:
    assert [format_for_output(Path(p)) for p in ("a.mp4", "b.GIF", "frames", "c.png")] == ["mp4", "gif", "png", "png"]
