"""Frames of an animation path: the camera and parameter values at each movie frame.

Camera. The view direction (unit vector from the origin to the camera) is interpolated on the
sphere: ``linear`` is slerp between consecutive keyframes, ``smooth`` a Catmull-Rom spline with
the keyframe times as knots, built from slerps (``splines.catmull_rom``): it passes through
every keyframe, stays on the sphere and is exact on great circles. Either way the camera takes
the shortest way between two keyframes, across azimuth +-180 and over the poles alike. Distance
and field of view are linear (``linear``) or monotone cubic (``smooth``: never beyond the
keyframe values, so the distance stays positive).

Roll. ``orbit_c2w`` holds the horizon level (its x axis is the azimuth tangent), so near a pole
its image spins as fast as the azimuth changes, and half a turn at once where a path crosses the
pole. A segment between two keyframes keeps the horizon level (each frame is ``orbit_c2w`` of its
view direction) while that turns the image at most ``MAX_LEVEL_SPIN`` degrees about the viewing
axis per degree the view direction moves (along a parallel: up to 75 degrees of elevation).
Otherwise the frame is the first keyframe's ``orbit_c2w`` carried along the direction curve by
parallel transport (no spin about the viewing axis), turned about the viewing axis by the roll
that closes the segment on the next keyframe's ``orbit_c2w``, spread evenly over the segment's
time: over a pole the image turns its half-turn gradually. Either way each keyframe's frame is
exactly ``orbit_c2w`` of its camera.

Parameters: ``linear`` or ``smooth`` (monotone cubic, ``splines.pchip``), always clamped to the
axis range.
"""

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from jaxtyping import Float

from visnerf.animation.keys import AnimationPath, AxisLike, CameraKey, PathError
from visnerf.animation.splines import catmull_rom, cross3, pchip, slerp, turn_between
from visnerf.data.cameras import orbit_c2w

TRANSPORT_STEP_DEG = 1.0
"""Largest turn of the view direction between two steps of the parallel transport along a
segment, and of the check of the level horizon's spin. Transport along chords of a curve of
geodesic curvature k, steps h apart, errs by about k h^2 / 12 radians per radian of curve: under
1e-4 radians at 1 degree."""
TRANSPORT_STEPS_PER_FRAME = 8
"""At most this many transport steps a frame of the segment (at least ``TRANSPORT_MIN_STEPS``)."""
TRANSPORT_MIN_STEPS = 32

MAX_FRAMES = 100_000
"""Most frames one path may give (an hour at about 28 fps)."""

MAX_LEVEL_SPIN = math.tan(math.radians(75.0))
"""Most degrees a level horizon may turn about the viewing axis per degree of view direction
(``tan(elevation)`` along a parallel) before a segment switches to the transported frame."""


@dataclass(frozen=True)
class FrameSpec:
    """What to render for one movie frame."""

    c2w: Float[np.ndarray, "4 4"]
    """Camera-to-world (float64, OpenGL axes) of an orbit camera looking at the origin."""
    fov_deg: float | None
    """Horizontal field of view in degrees of a perspective camera; None for an orthographic one."""
    params: dict[str, float]
    """Every axis' value, by name, within its range."""
    view_height: float | None = None
    """World units an orthographic camera's image spans vertically; None for a perspective one."""


def frame_times(path: AnimationPath, fps: float) -> list[float]:
    """``first + i / fps`` for i = 0 .. round(duration * fps): one frame for a single keyframe.
    Raises PathError for more than ``MAX_FRAMES`` frames."""
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a finite number above 0, got {fps}")
    count = round(path.duration * fps) + 1
    if count > MAX_FRAMES:
        raise PathError(f"keyframes: {path.duration:g} s at {fps:g} fps is {count} frames; at most {MAX_FRAMES}")
    first = path.keyframes[0].time
    return [first + i / fps for i in range(count)]


def direction(camera: CameraKey) -> Float[np.ndarray, " 3"]:
    """Unit vector from the origin to the camera (``orbit_c2w``'s z axis)."""
    az, el = math.radians(camera.azimuth), math.radians(camera.elevation)
    return np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])


def sample_frames(path: AnimationPath, fps: float, axes: Sequence[AxisLike]) -> list[FrameSpec]:
    """The frames at ``frame_times(path, fps)``; times past the last keyframe (rounding) hold it.

    Parameter names a keyframe leaves out take the axis default; a name that is no axis raises
    PathError.
    """
    keys = path.keyframes
    names = [a.name for a in axes]
    for i, key in enumerate(keys):
        unknown = sorted(set(key.params) - set(names))
        if unknown:
            raise PathError(f"keyframes[{i}].params.{unknown[0]}: unknown parameter; this scene has {sorted(names)}")
    camera = _CameraCurve(path, fps)
    times = np.array([k.time for k in keys])
    values = {a.name: np.array([float(k.params.get(a.name, a.default)) for k in keys]) for a in axes}
    frames = []
    for t in frame_times(path, fps):
        t = min(t, keys[-1].time)
        params = {a.name: _param_at(path.param_interpolation, times, values[a.name], a, t) for a in axes}
        c2w, lens = camera.at(t)
        frames.append(FrameSpec(c2w, None, params, lens) if path.orthographic else FrameSpec(c2w, lens, params))
    return frames


def _param_at(interpolation: str, times: np.ndarray, values: np.ndarray, axis: AxisLike, t: float) -> float:
    """One axis' value at ``t`` from its keyframe ``values``, clamped to the axis range."""
    value = pchip(times, values, t) if interpolation == "smooth" else float(np.interp(t, times, values))
    return min(max(value, float(axis.min)), float(axis.max))


class _CameraCurve:
    """The camera along a path; per segment, the transported frames are computed once."""

    def __init__(self, path: AnimationPath, fps: float) -> None:
        self.keys = path.keyframes
        self.fps = fps
        self.smooth = path.camera_interpolation == "smooth"
        self.times = [k.time for k in self.keys]
        self.dirs = [direction(k.camera) for k in self.keys]
        self.distances = np.array([k.camera.distance for k in self.keys])
        self.lenses = np.array([k.camera.lens for k in self.keys])
        self.time_array = np.array(self.times)
        self._segments: dict[int, tuple[list[float], list[np.ndarray], list[np.ndarray], float, bool]] = {}

    def at(self, t: float) -> tuple[np.ndarray, float]:
        """(c2w [4, 4], lens) at time ``t`` within the keyframes' times; the lens (field of view or
        view height, ``CameraKey.lens``) interpolates as the distance does."""
        k = max(0, min(bisect.bisect_right(self.times, t) - 1, len(self.keys) - 1))
        if abs(t - self.times[k]) <= 1e-9 * max(1.0, abs(t)) or k == len(self.keys) - 1:
            cam = self.keys[k].camera
            return orbit_c2w(cam.azimuth, cam.elevation, cam.distance), cam.lens
        times = self.time_array
        if self.smooth:
            distance, lens = pchip(times, self.distances, t), pchip(times, self.lenses, t)
        else:
            distance, lens = float(np.interp(t, times, self.distances)), float(np.interp(t, times, self.lenses))
        back = self.direction_at(k, t)
        knots, dirs, rights, closing, level = self._segment(k)
        if level:
            azimuth, elevation = _angles(back)
            return orbit_c2w(azimuth, elevation, distance), lens
        j = max(0, min(bisect.bisect_right(knots, t) - 1, len(knots) - 2))
        right = turn_between(dirs[j], back, rights[j])
        s = (t - self.times[k]) / (self.times[k + 1] - self.times[k])
        right = _roll(right, back, s * closing)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2] = right, cross3(back, right), back
        c2w[:3, 3] = distance * back
        return c2w, lens

    def direction_at(self, k: int, t: float) -> np.ndarray:
        """The view direction at ``t`` in segment ``k`` (keyframes k and k + 1)."""
        t1, t2 = self.times[k], self.times[k + 1]
        p1, p2 = self.dirs[k], self.dirs[k + 1]
        if not self.smooth:
            return slerp(p1, p2, (t - t1) / (t2 - t1))
        if k > 0:
            p0, t0 = self.dirs[k - 1], self.times[k - 1]
        else:  # a phantom key mirrors p2 through p1, as far before as p2 is after
            p0, t0 = slerp(p2, p1, 2.0), t1 - (t2 - t1)
        if k + 2 < len(self.keys):
            p3, t3 = self.dirs[k + 2], self.times[k + 2]
        else:
            p3, t3 = slerp(p1, p2, 2.0), t2 + (t2 - t1)
        out = catmull_rom((p0, p1, p2, p3), (t0, t1, t2, t3), t, slerp)
        return out / np.linalg.norm(out)

    def _segment(self, k: int) -> tuple[list[float], list[np.ndarray], list[np.ndarray], float, bool]:
        """Knot times, directions and transported x axes along segment ``k``, the roll (radians)
        that turns the transported x axis at its end onto the next keyframe's, and whether a level
        horizon spins slowly enough all along (``MAX_LEVEL_SPIN``)."""
        if k in self._segments:
            return self._segments[k]
        t1, t2 = self.times[k], self.times[k + 1]
        if self.smooth:  # the spline may bend beyond its keyframes' chord: allow for 1.5 times the longest
            turn = 1.5 * max(_angle(self.dirs[i], self.dirs[i + 1])
                             for i in range(max(k - 1, 0), min(k + 2, len(self.keys) - 1)))
        else:
            turn = _angle(self.dirs[k], self.dirs[k + 1])
        # Transport steps of TRANSPORT_STEP_DEG, but never many more than the segment has frames
        # (a path of hundreds of sharp turns took minutes to sample otherwise).
        frames = math.ceil((t2 - t1) * self.fps)
        most = max(TRANSPORT_MIN_STEPS, TRANSPORT_STEPS_PER_FRAME * frames)
        steps = int(min(max(math.ceil(math.degrees(turn) / TRANSPORT_STEP_DEG), 1), most, 2000))
        knots = [t1 + (t2 - t1) * j / steps for j in range(steps + 1)]
        dirs = [self.dirs[k], *(self.direction_at(k, tk) for tk in knots[1:-1]), self.dirs[k + 1]]
        rights = [_orbit_right(self.keys[k].camera)]
        for a, b in zip(dirs[:-1], dirs[1:], strict=True):
            r = turn_between(a, b, rights[-1])
            r = r - (r @ b) * b
            rights.append(r / np.linalg.norm(r))
        target = _orbit_right(self.keys[k + 1].camera)
        end, back = rights[-1], dirs[-1]
        closing = math.atan2(float(cross3(end, target) @ back), float(end @ target))
        self._segments[k] = (knots, dirs, rights, closing, _level_is_slow(dirs, rights))
        return self._segments[k]


def _level_is_slow(dirs: list[np.ndarray], rights: list[np.ndarray]) -> bool:
    """Whether the level horizon (``orbit_c2w``) along the directions turns, relative to the
    transported x axes, at most ``MAX_LEVEL_SPIN`` degrees per degree of direction."""
    rolls = []
    for back, right in zip(dirs, rights, strict=True):
        if math.hypot(back[0], back[2]) < 1e-6:
            return False  # at a pole: the level horizon is undefined
        azimuth, _ = _angles(back)
        level = _orbit_right_at(azimuth)
        rolls.append(math.atan2(float(cross3(right, level) @ back), float(right @ level)))
    for j in range(len(dirs) - 1):
        spin = abs(math.remainder(rolls[j + 1] - rolls[j], 2.0 * math.pi))
        if spin > MAX_LEVEL_SPIN * _angle(dirs[j], dirs[j + 1]) + 1e-9:
            return False
    return True


def _angles(back: np.ndarray) -> tuple[float, float]:
    """(azimuth, elevation) in degrees of a unit direction, as ``orbit_c2w`` takes them."""
    x, y, z = (float(c) for c in back)
    return math.degrees(math.atan2(x, z)), math.degrees(math.asin(max(-1.0, min(1.0, y))))


def _orbit_right(camera: CameraKey) -> np.ndarray:
    """``orbit_c2w``'s x axis: the azimuth tangent, defined at the poles too."""
    return _orbit_right_at(camera.azimuth)


def _orbit_right_at(azimuth_deg: float) -> np.ndarray:
    az = math.radians(azimuth_deg)
    return np.array([math.cos(az), 0.0, -math.sin(az)])


def _roll(right: np.ndarray, back: np.ndarray, angle: float) -> np.ndarray:
    """``right`` (perpendicular to unit ``back``) turned by ``angle`` radians about ``back``."""
    return right * math.cos(angle) + cross3(back, right) * math.sin(angle)


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return math.acos(float(np.clip(a @ b, -1.0, 1.0)))
