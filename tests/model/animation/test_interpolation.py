"""Frames of a path: count and times, keyframes exact, no jump at the poles or across azimuth 180,
parameters inside their ranges, and the ready-made paths."""

import json
import math

import numpy as np
import pytest

from visnerf.animation import interpolation
from visnerf.animation.path import (
    AnimationPath,
    CameraKey,
    Keyframe,
    PathError,
    frame_times,
    orbit_path,
    sample_frames,
    sweep_path,
)
from visnerf.animation.path import test_path as protocol_test_path
from visnerf.animation.splines import catmull_rom, lerp
from visnerf.checkpoint import ParamAxis
from visnerf.data.cameras import check_rigid_c2w, orbit_c2w, orbit_from_c2w
from visnerf.scenes.catalog import get_scene
from visnerf.scenes.writer import DatasetOptions, write_scene

AXES = (ParamAxis("a", 0.0, 1.0, (0.0, 0.5, 1.0), 0.5),)


def key(t: float, az: float, el: float, distance: float = 2.0, fov: float = 30.0, **params: float) -> Keyframe:
    return Keyframe(t, CameraKey(az, el, distance, fov), dict(params))


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle of the rotation between two camera orientations."""
    r = a[:3, :3].T @ b[:3, :3]
    return math.degrees(math.acos(float(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def view_step_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two cameras' directions from the origin."""
    da, db = a[:3, 3] / np.linalg.norm(a[:3, 3]), b[:3, 3] / np.linalg.norm(b[:3, 3])
    return math.degrees(math.acos(float(np.clip(da @ db, -1.0, 1.0))))


def direction(az: float, el: float) -> np.ndarray:
    return orbit_c2w(az, el, 1.0)[:3, 2]


@pytest.mark.parametrize("duration, fps, count", [(0.0, 30.0, 1), (1.0, 30.0, 31), (2.0, 24.0, 49), (1.01, 10.0, 11),
                                                   (1.06, 10.0, 12)])
def test_frame_count_and_times(duration: float, fps: float, count: int) -> None:
    keys = (key(0.5, 0.0, 0.0),) if duration == 0 else (key(0.5, 0.0, 0.0), key(0.5 + duration, 40.0, 0.0))
    path = AnimationPath(keys)
    times = frame_times(path, fps)
    assert len(times) == count == len(sample_frames(path, fps, AXES))
    np.testing.assert_allclose(times, 0.5 + np.arange(count) / fps)


def test_a_path_of_too_many_frames_is_refused() -> None:
    path = AnimationPath((key(0.0, 0.0, 0.0), key(1e6, 10.0, 0.0)))
    with pytest.raises(PathError, match=r"^keyframes: 1e\+06 s at 30 fps is 30000001 frames; at most 100000"):
        sample_frames(path, 30.0, AXES)


def test_frames_at_keyframe_times_are_the_keyframe_cameras_exactly() -> None:
    path = AnimationPath((key(0.0, 10.0, 20.0, 2.0, 30.0, a=0.1), key(0.5, 100.0, -30.0, 3.0, 50.0, a=0.9),
                          key(1.0, -150.0, 90.0, 2.5, 20.0, a=0.4)), camera_interpolation="smooth")
    frames = sample_frames(path, 10.0, AXES)
    for frame, k in zip((frames[0], frames[5], frames[10]), path.keyframes, strict=True):
        np.testing.assert_array_equal(frame.c2w, orbit_c2w(k.camera.azimuth, k.camera.elevation, k.camera.distance))
        assert frame.fov_deg == k.camera.fov and frame.params == k.params
    for frame in frames:
        check_rigid_c2w(frame.c2w, tol=1e-9)
        # every frame looks at the origin
        np.testing.assert_allclose(frame.c2w[:3, 2], frame.c2w[:3, 3] / np.linalg.norm(frame.c2w[:3, 3]), atol=1e-12)


@pytest.mark.parametrize("interpolation", ["linear", "smooth"])
@pytest.mark.parametrize("start, end", [((0.0, 80.0), (180.0, 80.0)), ((0.0, 50.0), (180.0, 50.0)),
                                        ((0.0, 80.0), (170.0, 80.0)), ((179.0, 10.0), (-179.0, 10.0)),
                                        ((30.0, -85.0), (-140.0, -75.0))])
def test_two_keyframes_move_the_short_way_without_a_jump(interpolation: str, start: tuple, end: tuple) -> None:
    n = 31
    path = AnimationPath((key(0.0, *start), key(1.0, *end)), camera_interpolation=interpolation)
    frames = sample_frames(path, float(n - 1), AXES)
    total = math.degrees(math.acos(float(np.clip(direction(*start) @ direction(*end), -1, 1))))
    # the direction moves along the shortest arc at a constant rate: each step is total / (n - 1)
    for a, b in zip(frames[:-1], frames[1:], strict=True):
        assert view_step_deg(a.c2w, b.c2w) == pytest.approx(total / (n - 1), abs=1e-6)
    # the image turns about its axis by at most the roll that closes the segment (half a turn over
    # a pole) spread over the steps, on top of the direction's step
    bound = (total + 180.0) / (n - 1) + 1e-6
    assert max(rotation_deg(a.c2w, b.c2w) for a, b in zip(frames[:-1], frames[1:], strict=True)) <= bound


def test_a_level_horizon_alone_would_spin_over_the_pole() -> None:
    """What the bound above guards against: ``orbit_c2w`` of the same directions turns the image
    half a turn between two frames where the path crosses the pole."""
    frames = sample_frames(AnimationPath((key(0.0, 0.0, 80.0), key(1.0, 180.0, 80.0))), 30.0, AXES)
    level = [orbit_c2w(*orbit_from_c2w(f.c2w)) for f in frames]
    assert max(rotation_deg(a, b) for a, b in zip(level[:-1], level[1:], strict=True)) > 170.0
    assert max(rotation_deg(a.c2w, b.c2w) for a, b in zip(frames[:-1], frames[1:], strict=True)) < 8.0


def test_away_from_the_poles_the_horizon_stays_level() -> None:
    path = AnimationPath((key(0.0, 0.0, 30.0), key(1.0, 90.0, 30.0), key(2.0, 200.0, 10.0)), "smooth")
    for frame in sample_frames(path, 20.0, AXES):
        assert abs(frame.c2w[1, 0]) < 1e-12  # the camera's x axis is horizontal


def test_a_winding_smooth_path_over_a_pole_has_no_abrupt_step() -> None:
    keys = (key(0.0, 0.0, 60.0), key(1.0, 90.0, 85.0), key(2.0, 230.0, 75.0), key(3.0, 280.0, 40.0),
            key(3.5, 300.0, 89.0))
    frames = sample_frames(AnimationPath(keys, "smooth"), 60.0, AXES)
    steps = [rotation_deg(a.c2w, b.c2w) for a, b in zip(frames[:-1], frames[1:], strict=True)]
    assert max(steps) < 4.0 * float(np.mean(steps))  # no step stands out: no spin, no flip
    view = [view_step_deg(a.c2w, b.c2w) for a, b in zip(frames[:-1], frames[1:], strict=True)]
    assert max(view) < 4.0 * float(np.mean(view))


def test_smooth_parameters_never_leave_their_range() -> None:
    values = [0.0, 1.0, 1.0, 0.0, 0.97, 0.02, 1.0]  # plateaus and reversals: a classical spline overshoots
    times = [0.0, 0.3, 0.6, 0.7, 1.5, 1.6, 2.0]
    keys = tuple(key(t, 0.0, 0.0, a=v) for t, v in zip(times, values, strict=True))
    frames = sample_frames(AnimationPath(keys, param_interpolation="smooth"), 100.0, AXES)
    got = [f.params["a"] for f in frames]
    assert min(got) >= 0.0 and max(got) <= 1.0
    # the same data through a Catmull-Rom spline leave [0, 1]: the data do provoke overshoot
    classical = [float(catmull_rom((np.array([values[k - 1]]), np.array([values[k]]), np.array([values[k + 1]]),
                                    np.array([values[k + 2]])), (times[k - 1], times[k], times[k + 1], times[k + 2]),
                                   float(t), lerp)[0])
                 for k in range(1, len(values) - 2) for t in np.linspace(times[k], times[k + 1], 20)]
    assert min(classical) < -0.01 or max(classical) > 1.01


def test_linear_parameters_and_defaults() -> None:
    axes = (*AXES, ParamAxis("b", -1.0, 1.0, (-1.0, 1.0), 0.25))
    frames = sample_frames(AnimationPath((key(0.0, 0.0, 0.0, a=0.2), key(1.0, 0.0, 0.0, a=0.6))), 4.0, axes)
    np.testing.assert_allclose([f.params["a"] for f in frames], [0.2, 0.3, 0.4, 0.5, 0.6])
    assert all(f.params["b"] == 0.25 for f in frames)


def test_an_unknown_parameter_in_a_built_path_is_named() -> None:
    with pytest.raises(PathError, match=r"^keyframes\[0\]\.params\.zz: unknown parameter"):
        sample_frames(AnimationPath((key(0.0, 0.0, 0.0, zz=1.0),)), 30.0, AXES)


@pytest.mark.parametrize("n_frames", [1, 7, 36, 1003])
def test_orbit_turns_once_without_repeating_a_frame(n_frames: int) -> None:
    path = orbit_path(n_frames, 24.0, 25.0, 2.2, 35.0, {"a": 0.3}, start_azimuth=-30.0)
    frames = sample_frames(path, 24.0, AXES)
    assert len(frames) == n_frames
    for i, frame in enumerate(frames):
        azimuth, elevation, distance = orbit_from_c2w(frame.c2w)
        # every frame is a keyframe up to 1000 frames; beyond, slerp between keyframes 0.7 degrees
        # apart leaves the parallel by 4e-4 degrees
        assert math.remainder(azimuth - (-30.0 + 360.0 * i / n_frames), 360.0) == pytest.approx(0.0, abs=1e-3)
        assert elevation == pytest.approx(25.0, abs=1e-3) and distance == pytest.approx(2.2)
        assert frame.fov_deg == 35.0 and frame.params == {"a": 0.3}
    if n_frames > 1:  # the next frame after the last would be the first again
        step = 360.0 / n_frames
        last_az = orbit_from_c2w(frames[-1].c2w)[0]
        assert math.remainder(last_az + step - (-30.0), 360.0) == pytest.approx(0.0, abs=1e-6)
        assert rotation_deg(frames[-1].c2w, frames[0].c2w) > 0.5 * rotation_deg(frames[0].c2w, frames[1].c2w)


def test_sweep_moves_one_axis_from_min_to_max_at_a_fixed_camera() -> None:
    axes = (*AXES, ParamAxis("b", -1.0, 3.0, (-1.0, 3.0), 0.0))
    camera = CameraKey(40.0, 10.0, 2.0, 30.0)
    frames = sample_frames(sweep_path("b", 5, 30.0, axes, camera, {"a": 0.9}), 30.0, axes)
    np.testing.assert_allclose([f.params["b"] for f in frames], [-1.0, 0.0, 1.0, 2.0, 3.0])
    assert all(f.params["a"] == 0.9 for f in frames)
    for f in frames:
        np.testing.assert_allclose(f.c2w, orbit_c2w(40.0, 10.0, 2.0), atol=1e-12)
    with pytest.raises(PathError, match="unknown parameter 'c'"):
        sweep_path("c", 5, 30.0, axes, camera, {})


def test_the_test_path_is_the_generated_scenes_test_split(tmp_path) -> None:
    spec = get_scene("cosmo_sim")  # three axes: the protocol's one-at-a-time and together halves
    write_scene(spec, tmp_path, DatasetOptions(resolution=8, n_views=12, n_test_views=9))
    test_split = json.loads((tmp_path / "transforms_test.json").read_text())
    axes = tuple(ParamAxis(a.name, a.low, a.high, a.values(), a.values()[1]) for a in spec.axes)
    path = protocol_test_path(9, axes, spec.camera_distance, spec.fov_x_deg, fps=30.0)
    frames = sample_frames(path, 30.0, axes)
    assert len(frames) == len(test_split["frames"]) == 9
    for frame, truth in zip(frames, test_split["frames"], strict=True):
        np.testing.assert_allclose(frame.c2w, truth["transform_matrix"], atol=1e-12)
        np.testing.assert_allclose([frame.params[a.name] for a in axes], truth["params"], atol=1e-12)
        assert math.radians(frame.fov_deg) == pytest.approx(test_split["camera_angle_x"])


def test_the_transport_steps_are_fine_enough(monkeypatch) -> None:
    """The frames with the default transport step against ten times finer steps (the slow reference)."""
    keys = (key(0.0, 0.0, 60.0), key(1.0, 90.0, 85.0), key(2.0, 230.0, 75.0), key(3.0, 280.0, 40.0))
    path = AnimationPath(keys, "smooth")
    coarse = sample_frames(path, 15.0, AXES)
    monkeypatch.setattr(interpolation, "TRANSPORT_STEP_DEG", interpolation.TRANSPORT_STEP_DEG / 10.0)
    fine = sample_frames(path, 15.0, AXES)
    assert max(rotation_deg(a.c2w, b.c2w) for a, b in zip(coarse, fine, strict=True)) < 0.02
