"""Ready-made animation paths: a turn around the scene, a sweep of one parameter, and the
evaluation protocol's winding test path."""

import math
from collections.abc import Mapping, Sequence

from visnerf.animation.keys import MAX_KEYFRAMES, AnimationPath, AxisLike, CameraKey, Keyframe, PathError
from visnerf.scenes.protocol import ParamAxis as ProtocolAxis
from visnerf.scenes.protocol import path_angles, path_params


def _check_frames(n_frames: int, fps: float, least: int) -> None:
    if n_frames < least:
        raise ValueError(f"n_frames must be at least {least}, got {n_frames}")
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a finite number above 0, got {fps}")


def orbit_path(
    n_frames: int,
    fps: float,
    elevation: float,
    distance: float,
    fov: float | None,
    params: Mapping[str, float],
    start_azimuth: float = 0.0,
    view_height: float | None = None,
) -> AnimationPath:
    """One full turn in azimuth at a fixed elevation: ``n_frames`` frames at ``fps``, frame i at
    azimuth ``start_azimuth + 360 i / n_frames`` (the last frame does not repeat the first, so the
    movie loops); ``view_height`` instead of ``fov`` for an orthographic camera. Every frame is a
    keyframe while there are at most ``MAX_KEYFRAMES`` of them (so the camera keeps its elevation
    exactly), else every k-th frame and the last."""
    _check_frames(n_frames, fps, 1)
    step = max(1, math.ceil((n_frames - 1) / (MAX_KEYFRAMES - 1)))
    indices = sorted({*range(0, n_frames, step), n_frames - 1})
    keyframes = tuple(
        Keyframe(i / fps, CameraKey(start_azimuth + 360.0 * i / n_frames, elevation, distance, fov, view_height),
                 dict(params))
        for i in indices
    )
    return AnimationPath(keyframes, camera_interpolation="linear", param_interpolation="linear")


def sweep_path(
    axis_name: str,
    n_frames: int,
    fps: float,
    axes: Sequence[AxisLike],
    camera: CameraKey,
    params: Mapping[str, float],
) -> AnimationPath:
    """The named axis from its min (first frame) to its max (last frame, ``n_frames`` >= 2 frames
    at ``fps``), evenly; the camera and the other parameters (``params``, else their defaults) stay."""
    _check_frames(n_frames, fps, 2)
    by_name = {a.name: a for a in axes}
    if axis_name not in by_name:
        raise PathError(f"sweep: unknown parameter {axis_name!r}; this scene has {sorted(by_name)}")
    fixed = {a.name: float(params.get(a.name, a.default)) for a in axes}
    axis = by_name[axis_name]
    first = Keyframe(0.0, camera, {**fixed, axis_name: float(axis.min)})
    last = Keyframe((n_frames - 1) / fps, camera, {**fixed, axis_name: float(axis.max)})
    return AnimationPath((first, last), camera_interpolation="linear", param_interpolation="linear")


def test_path(n_views: int, axes: Sequence[AxisLike], distance: float, fov: float | None, fps: float = 30.0,
              view_height: float | None = None) -> AnimationPath:
    """The evaluation protocol's test path (``visnerf.scenes.protocol``): ``n_views`` keyframes
    ``1 / fps`` apart, so ``sample_frames(path, fps, axes)`` gives exactly the cameras
    (``orbit_c2w(azimuth, elevation, distance)``) and parameter values of a generated scene's
    test split. Each axis needs ``values`` (its training values: the protocol keeps the test
    values between them), as the checkpoint's ``ParamAxis`` has."""
    _check_frames(n_views, fps, 2)
    protocol_axes = []
    for axis in axes:
        values = getattr(axis, "values", None)
        if values is None or len(values) < 2:
            raise ValueError(f"test_path needs the training values of axis {axis.name!r} (at least two)")
        protocol_axes.append(ProtocolAxis(axis.name, float(axis.min), float(axis.max), len(values)))
    angles = path_angles(n_views)
    settings = path_params(tuple(protocol_axes), n_views)
    keyframes = tuple(
        Keyframe(i / fps, CameraKey(az, el, distance, fov, view_height),
                 {a.name: float(v) for a, v in zip(axes, setting, strict=True)})
        for i, ((az, el), setting) in enumerate(zip(angles, settings, strict=True))
    )
    return AnimationPath(keyframes, camera_interpolation="linear", param_interpolation="linear")


test_path.__test__ = False  # type: ignore[attr-defined]  # a path maker, not a test, where a test module imports it
