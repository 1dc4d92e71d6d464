"""``visnerf animate`` on a tiny checkpoint: the movie read back against renders of its keyframes,
GIF and PNG outputs, Ctrl-C, and bad inputs refused with nothing written."""

import argparse
import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import av
import numpy as np
import pytest
from PIL import Image

from visnerf.animation import commands
from visnerf.data.cameras import orbit_c2w
from visnerf.inference import SceneRenderer, load_scene
from visnerf.testing import make_tiny_checkpoint

AXES = [("a", [0.0, 0.5, 1.0]), ("b", [1.0, 2.0])]
PATH_DOC = {
    "version": 1,
    "camera_interpolation": "smooth",
    "param_interpolation": "linear",
    "keyframes": [
        {"time": 0.0, "camera": {"azimuth": 30, "elevation": 15, "distance": 2.2, "fov": 30}, "params": {"a": 0.1}},
        {"time": 0.5, "camera": {"azimuth": 100, "elevation": 40, "distance": 2.6, "fov": 35},
         "params": {"a": 0.9, "b": 1.5}},
    ],
}


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # small renders: one thread (conftest)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("inputs")
    make_tiny_checkpoint(folder / "tiny.safetensors", AXES)
    (folder / "path.json").write_text(json.dumps(PATH_DOC))
    return folder


def run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="visnerf")
    commands.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse)


def render_key(scene: SceneRenderer, key: dict, size: int) -> np.ndarray:
    cam = key["camera"]
    c2w = orbit_c2w(float(cam["azimuth"]), float(cam["elevation"]), float(cam["distance"]))
    return scene.render(c2w, float(cam["fov"]), size, size, {k: float(v) for k, v in key["params"].items()})


@pytest.mark.slow
def test_an_mp4_from_the_command_line_matches_renders_of_its_keyframes(inputs: Path, tmp_path: Path) -> None:
    out = tmp_path / "movie.mp4"
    done = subprocess.run(
        [sys.executable, "-m", "visnerf.cli", "animate", str(inputs / "tiny.safetensors"), "--path",
         str(inputs / "path.json"), "--fps", "10", "--size", "32x32", "--device", "cpu", "-o", str(out)],
        capture_output=True, text=True, timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "frame/s" in done.stderr  # the progress bar
    with av.open(str(out)) as container:
        stream = container.streams.video[0]
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
        rate = stream.average_rate
    assert rate == 10 and len(frames) == 6 and frames[0].shape == (32, 32, 3)  # 0.5 s at 10 fps, both ends
    scene = load_scene(inputs / "tiny.safetensors")
    first, last = (render_key(scene, k, 32) for k in PATH_DOC["keyframes"])
    assert psnr(frames[0], first) > 30.0 and psnr(frames[-1], last) > 30.0
    assert psnr(frames[0], last) < psnr(frames[0], first) - 3.0  # the two ends do differ
    assert sorted(p.name for p in tmp_path.iterdir()) == ["movie.mp4"]


def test_an_orbit_gif(inputs: Path, tmp_path: Path) -> None:
    out = tmp_path / "turn.gif"
    assert run(["animate", str(inputs / "tiny.safetensors"), "--orbit", "4", "--size", "24x20", "--elevation", "10",
                "--param", "a=0.2", "--quality", "preview", "--quiet", "--device", "cpu", "-o", str(out)]) == 0
    with Image.open(out) as gif:
        assert gif.n_frames == 4 and gif.size == (24, 20)


def test_a_sweep_into_a_folder_of_pngs(inputs: Path, tmp_path: Path) -> None:
    out = tmp_path / "frames"
    assert run(["animate", str(inputs / "tiny.safetensors"), "--sweep", "b", "--frames", "3", "--size", "16x16",
                "--azimuth", "45", "--elevation", "20", "--quiet", "--device", "cpu", "-o", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == [f"frame_{i:05d}.png" for i in range(3)]
    scene = load_scene(inputs / "tiny.safetensors")
    cam = scene.info.camera
    expected = scene.render(orbit_c2w(45.0, 20.0, cam["distance"]), cam["fov_deg"], 16, 16, {"b": 2.0})
    assert psnr(np.asarray(Image.open(out / "frame_00002.png")), expected) > 40.0


def test_ctrl_c_keeps_a_playable_movie_of_the_frames_done(inputs: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    original = SceneRenderer.render
    calls = {"n": 0}

    def render_then_interrupt(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        return original(self, *args, **kwargs)

    monkeypatch.setattr(SceneRenderer, "render", render_then_interrupt)
    out = tmp_path / "m.mp4"
    assert run(["animate", str(inputs / "tiny.safetensors"), "--orbit", "8", "--size", "16x16", "--quiet",
                "--device", "cpu", "-o", str(out)]) == 130
    assert "interrupted after 3 of 8 frames" in capsys.readouterr().err
    with av.open(str(out)) as container:
        assert len(list(container.decode(video=0))) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.mp4"]


@pytest.mark.slow
def test_a_real_ctrl_c_on_the_command_line(inputs: Path, tmp_path: Path) -> None:
    """SIGINT once the progress bar shows a few frames: exit 130, a movie of the frames it names."""
    out = tmp_path / "m.mp4"
    proc = subprocess.Popen(
        [sys.executable, "-m", "visnerf.cli", "animate", str(inputs / "tiny.safetensors"), "--orbit", "3000",
         "--size", "16x16", "--device", "cpu", "-o", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # a background job may ignore it
    )
    assert proc.stderr is not None
    shown = ""
    while not re.search(r"\b([3-9]|\d{2,})/3000\b", shown):
        char = proc.stderr.read(1)
        if not char:
            break
        shown += char
    proc.send_signal(signal.SIGINT)
    shown += proc.stderr.read()
    assert proc.wait(timeout=60) == 130, shown
    done = re.search(r"interrupted after (\d+) of 3000 frames: .* holds a playable movie", shown)
    assert done is not None, shown
    with av.open(str(out)) as container:
        assert len(list(container.decode(video=0))) == int(done.group(1)) >= 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.mp4"]


def bad_path_file(folder: Path, text: str) -> str:
    """``text`` written to a path file in ``folder`` (before the test takes its listing)."""
    path = folder / "bad.json"
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize(
    "make_args, output, message",
    [
        (lambda d: ["--path", str(d / "missing.json")], "m.mp4", "cannot read the path file"),
        (lambda d: ["--path", bad_path_file(d, "{not json")], "m.mp4", "is not valid JSON"),
        (lambda d: ["--path", bad_path_file(d, json.dumps({**PATH_DOC, "keyframes": [
            {"time": 0, "camera": {"elevation": 120}}]}))], "m.mp4",
         "keyframes[0].camera.elevation: must be in [-90, 90], got 120"),
        (lambda d: ["--path", bad_path_file(d, json.dumps({**PATH_DOC, "version": 3}))], "m.gif", "version: must be 1"),
        (lambda d: ["--orbit", "3", "--size", "33x32"], "m.mp4", "even width and height"),
        (lambda d: ["--orbit", "3", "--size", "big"], "m.mp4", "--size must be WxH"),
        (lambda d: ["--sweep", "zz"], "frames", "unknown parameter 'zz'"),
        (lambda d: ["--orbit", "3", "--param", "zz=1"], "m.mp4", "--param zz: unknown parameter"),
        (lambda d: ["--orbit", "3", "--param", "a=7"], "m.mp4", "--param a: must be in [0, 1], got 7"),
        (lambda d: ["--orbit", "3", "--param", "a"], "m.mp4", "must be NAME=NUMBER"),
        (lambda d: ["--orbit", "3", "--elevation", "95"], "m.mp4", "camera.elevation: must be in [-90, 90]"),
        (lambda d: ["--test-path", "--param", "a=0.5"], "m.mp4", "--param sets the values of --orbit and --sweep"),
        (lambda d: ["--orbit", "3"], "out/", "exists: the PNG frames need a new or empty folder"),
        (lambda d: ["--orbit", "3"], "nowhere/m.mp4", "does not exist"),
    ],
)
def test_bad_input_exits_2_and_writes_nothing(inputs: Path, tmp_path: Path, capsys, make_args, output: str,
                                              message: str) -> None:
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    args = make_args(tmp_path)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    code = run(["animate", str(inputs / "tiny.safetensors"), *args, "--quiet",
                "--device", "cpu", "-o", str(tmp_path / output)])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: ") and message in err, err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_a_file_that_is_no_checkpoint_exits_2(tmp_path: Path, capsys) -> None:
    (tmp_path / "fake.safetensors").write_bytes(b"not a checkpoint")
    assert run(["animate", str(tmp_path / "fake.safetensors"), "--orbit", "3", "-o", str(tmp_path / "m.mp4")]) == 2
    assert capsys.readouterr().err.startswith("error: ")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fake.safetensors"]


@pytest.mark.parametrize("argv", [["--orbit", "0"], ["--orbit", "3", "--fps", "0"], ["--test-path", "1"],
                                  ["--orbit", "3", "--sweep", "a"], []])
def test_bad_arguments_are_refused_by_the_parser(tmp_path: Path, argv: list[str]) -> None:
    with pytest.raises(SystemExit) as caught:
        run(["animate", str(tmp_path / "x.safetensors"), *argv, "-o", str(tmp_path / "m.mp4")])
    assert caught.value.code == 2
    assert list(tmp_path.iterdir()) == []
