"""Orthographic movie paths: a keyframe's ``view_height`` in place of ``fov``, one projection per
path, the scene's lens for keyframes that name none, and ``visnerf animate`` rendering the frames
the renderer makes with that view height."""

import argparse
import math

import numpy as np
import pytest
from PIL import Image

from visnerf.animation import commands
from visnerf.animation.path import CameraKey, PathError, orbit_path, parse_path, sample_frames
from visnerf.checkpoint import ParamAxis
from visnerf.data.cameras import orbit_c2w
from visnerf.inference import load_scene
from visnerf.testing import make_tiny_checkpoint

AXES = (ParamAxis("a", 0.0, 1.0, (0.0, 1.0), 0.5),)
ORTHO_SCENE = {"azimuth": 30.0, "elevation": 20.0, "distance": 2.5, "view_height": 1.4}
PERSPECTIVE_SCENE = {"azimuth": 30.0, "elevation": 20.0, "distance": 2.5, "fov_deg": 30.0}


def doc(*cameras: dict) -> dict:
    return {"version": 1, "camera_interpolation": "linear",
            "keyframes": [{"time": float(i), "camera": c} for i, c in enumerate(cameras)]}


def test_view_heights_interpolate_like_the_distance() -> None:
    path = parse_path(doc({"azimuth": 0, "view_height": 1.0}, {"azimuth": 40, "view_height": 2.0}), AXES,
                      PERSPECTIVE_SCENE)
    assert path.orthographic and path.keyframes[0].camera == CameraKey(0.0, 20.0, 2.5, None, 1.0)
    frames = sample_frames(path, 4.0, AXES)
    assert [f.fov_deg for f in frames] == [None] * 5
    assert [f.view_height for f in frames] == pytest.approx([1.0, 1.25, 1.5, 1.75, 2.0])
    assert path.to_dict()["keyframes"][1]["camera"] == {"azimuth": 40.0, "elevation": 20.0, "distance": 2.5,
                                                        "view_height": 2.0}
    assert parse_path(path.to_dict(), AXES, PERSPECTIVE_SCENE) == path


def test_keyframes_without_a_lens_take_the_scenes() -> None:
    own = parse_path(doc({"azimuth": 0}, {"azimuth": 90}), AXES, ORTHO_SCENE)
    assert own.orthographic and {k.camera.view_height for k in own.keyframes} == {1.4}
    # a perspective path over an orthographic scene: the field of view framing it alike
    named = parse_path(doc({"azimuth": 0, "fov": 20}, {"azimuth": 90}), AXES, ORTHO_SCENE)
    assert not named.orthographic and named.keyframes[0].camera.fov == 20.0
    assert named.keyframes[1].camera.fov == pytest.approx(math.degrees(2 * math.atan(0.7 / 2.5)))
    # and the other way round
    ortho = parse_path(doc({"view_height": 3.0}, {}), AXES, PERSPECTIVE_SCENE)
    assert ortho.keyframes[1].camera.view_height == pytest.approx(2 * 2.5 * math.tan(math.radians(15.0)))


@pytest.mark.parametrize(("cameras", "message"), [
    (({"fov": 30}, {"view_height": 1.0}), "keyframes[1].camera.view_height: keyframes[0] has a fov"),
    (({"view_height": 1.0}, {"fov": 30}), "keyframes[1].camera.fov: keyframes[0] has a view_height"),
    (({"fov": 30, "view_height": 1.0},), "keyframes[0].camera: give fov (perspective) or view_height"),
    (({"view_height": 0},), "keyframes[0].camera.view_height: must be above 0"),
    (({"view_height": "wide"},), "keyframes[0].camera.view_height"),
])
def test_bad_lenses_are_refused_naming_the_field(cameras: tuple, message: str) -> None:
    with pytest.raises(PathError) as info:
        parse_path(doc(*cameras), AXES, ORTHO_SCENE)
    assert message in str(info.value)


def test_a_camera_names_exactly_one_lens() -> None:
    with pytest.raises(PathError, match="exactly one"):
        CameraKey(0.0, 0.0, 2.0)
    with pytest.raises(PathError, match="exactly one"):
        CameraKey(0.0, 0.0, 2.0, 30.0, 1.0)
    assert orbit_path(4, 4.0, 10.0, 2.0, None, {}, view_height=1.2).orthographic


def max_difference(a: np.ndarray, b: np.ndarray) -> int:
    return int(np.abs(a.astype(np.int64) - b.astype(np.int64)).max())


def run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="visnerf")
    commands.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.mark.usefixtures("one_torch_thread")
def test_animate_renders_an_orthographic_scene_orthographic(tmp_path) -> None:
    ckpt = make_tiny_checkpoint(tmp_path / "flat.safetensors", [("a", [0.0, 1.0])], camera=ORTHO_SCENE)
    scene = load_scene(ckpt)
    out = tmp_path / "frames"
    assert run(["animate", str(ckpt), "--orbit", "4", "--size", "20x16", "--quiet", "--device", "cpu",
                "-o", str(out)]) == 0
    c2w = orbit_c2w(30.0 + 90.0, 20.0, 2.5)
    expected = scene.render(c2w, None, 20, 16, {"a": 0.5}, view_height=1.4)
    got = np.asarray(Image.open(out / "frame_00001.png"))
    assert max_difference(got, expected) <= 3  # rounding of chunked sums
    assert max_difference(got, scene.render(c2w, 30.0, 20, 16, {"a": 0.5})) > 30
    wide = tmp_path / "wide"
    assert run(["animate", str(ckpt), "--orbit", "4", "--size", "20x16", "--view-height", "2.8", "--quiet",
                "--device", "cpu", "-o", str(wide)]) == 0
    wide_frame = np.asarray(Image.open(wide / "frame_00001.png"))
    assert max_difference(wide_frame, scene.render(c2w, None, 20, 16, {"a": 0.5}, view_height=2.8)) <= 3
    assert max_difference(wide_frame, got) > 30
