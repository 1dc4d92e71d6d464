"""Movie paths, the public face: the format (``keys``), its reader (``parse``), the frames it
describes (``interpolation``) and ready-made paths (``presets``).

    path = parse_path(json.loads(text), scene.info.params, scene.info.camera)
    for frame in sample_frames(path, fps=30.0, axes=scene.info.params):
        scene.render(frame.c2w, frame.fov_deg, 256, 256, frame.params, view_height=frame.view_height)
"""

from visnerf.animation.interpolation import MAX_FRAMES, FrameSpec, frame_times, sample_frames
from visnerf.animation.keys import (
    MAX_KEYFRAMES,
    PATH_VERSION,
    AnimationPath,
    AxisLike,
    CameraKey,
    Keyframe,
    PathError,
)
from visnerf.animation.parse import parse_path
from visnerf.animation.presets import orbit_path, sweep_path, test_path

__all__ = [
    "MAX_FRAMES",
    "MAX_KEYFRAMES",
    "PATH_VERSION",
    "AnimationPath",
    "AxisLike",
    "CameraKey",
    "FrameSpec",
    "Keyframe",
    "PathError",
    "frame_times",
    "orbit_path",
    "parse_path",
    "sample_frames",
    "sweep_path",
    "test_path",
]
