"""The public inference API: what the server (and any script) uses to render a trained scene.

    scene = load_scene("checkpoints/vortex_tf.safetensors", torch.device("cpu"))
    scene.info.params            # parameter axes: name, min, max, training values, default
    image = scene.render(c2w, fov_deg=30, width=256, height=256, params={"opacity_a": 0.4})
    image.shape, image.dtype     # (256, 256, 3), uint8

A caller that checks a request before it renders it (the server) splits ``render`` in two:
``view`` checks the frame once and returns a ``FrameView``, ``draw`` renders it.

Nothing here reaches into training code.
"""

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from visnerf.checkpoint import CheckpointError, CheckpointMeta, ParamAxis, load_checkpoint
from visnerf.config import FramesConfig
from visnerf.data.cameras import Intrinsics, check_rigid_c2w
from visnerf.lens import Projection, choose_lens
from visnerf.rendering.cancel import CancelCheck, RenderCancelled
from visnerf.rendering.empty_space import EmptySpace
from visnerf.rendering.render_settings import Quality, RenderSettings
from visnerf.rendering.renderer import render_image_scaled
from visnerf.rendering.setting_occupancy import GridBuild, SettingOccupancy
from visnerf.representation import output_kernel, vm_kernel
from visnerf.representation.field import VisNerfField
from visnerf.runtime import release_free_memory

__all__ = [
    "CancelCheck",
    "CheckpointError",
    "EmptySpace",
    "FrameView",
    "GridBuild",
    "ParamAxis",
    "Projection",
    "Quality",
    "RenderCancelled",
    "SceneInfo",
    "SceneRenderer",
    "choose_lens",
    "load_scene",
]


@dataclass(frozen=True)
class SceneInfo:
    """Everything a client needs to know to explore a scene."""

    title: str
    kind: str
    """``dvr`` (direct volume rendering) or ``ir`` (isosurface rendering)."""
    params: tuple[ParamAxis, ...]
    camera: dict[str, float]
    """Default camera: azimuth, elevation, distance (orbit degrees), and fov_deg, or view_height for
    a scene trained from orthographic images."""
    bbox: tuple[tuple[float, float, float], tuple[float, float, float]]
    image_size: tuple[int, int]
    """(width, height) of the training images."""
    background: tuple[float, float, float]
    training: dict[str, object]
    """Provenance: dataset, iterations, train_seconds, val_psnr."""


def _scene_info(meta: CheckpointMeta) -> SceneInfo:
    params = tuple(
        ParamAxis(a.name, a.min, a.max, tuple(a.values), a.default) for a in meta.param_axes
    )
    return SceneInfo(
        title=meta.title,
        kind=meta.kind,
        params=params,
        camera=dict(meta.camera),
        bbox=(tuple(meta.bbox[0]), tuple(meta.bbox[1])),  # type: ignore[arg-type]
        image_size=(meta.image_width, meta.image_height),
        background=tuple(meta.background),  # type: ignore[arg-type]
        training=meta.provenance.to_dict(),
    )


@dataclass(frozen=True)
class FrameView:
    """A frame checked against its scene (``SceneRenderer.view``): ``draw`` renders it as it is."""

    c2w: np.ndarray
    """[4, 4] float64, a rigid camera-to-world matrix in OpenGL axes."""
    fov_deg: float | None
    """Horizontal field of view of a perspective frame; None for an orthographic one."""
    view_height: float | None
    """World units an orthographic frame spans vertically; None for a perspective one."""
    width: int
    height: int
    values: tuple[float, ...]
    """Every parameter's value in axis order, defaults filled in, within the training range."""
    quality: Quality


TRIM_AFTER_PIXELS = 512 * 512
"""Frames of at least this many pixels give their freed memory back to the system when done
(``runtime.release_free_memory``). A large frame allocates hundreds of megabytes in many blocks, on
the calling thread and the chunk threads, each served from a glibc arena of its own; freed, they
stayed resident and a server's memory grew frame after frame (docs/decisions.md#runtime.trim,
bench/results/server_load.md). Trimming takes milliseconds; smaller frames reuse the same blocks
frame after frame."""


class SceneRenderer:
    """A loaded scene. ``render`` and ``draw`` are thread safe: frames of any quality render at once
    (they read the field; the cache of setting grids has its own lock)."""

    def __init__(
        self,
        field: VisNerfField,
        meta: CheckpointMeta,
        device: torch.device,
        frames: FramesConfig | None = None,
    ) -> None:
        self.field = field.eval()
        if vm_kernel.available(device):
            vm_kernel.warm_up((field.cfg.n_density_components, field.cfg.n_appearance_components))
            output_kernel.warm_up()
        self.meta = meta
        self.device = device
        self.info = _scene_info(meta)
        self.frames = frames or FramesConfig()
        """This machine's chunks of rays and per-setting grids (``config.FramesConfig``)."""
        self.setting_occupancy = SettingOccupancy(self.field, self.frames, meta.render.occupancy_threshold)
        """Full-quality frames at a parameter tuple asked for more than once march that tuple's own
        occupancy grid (``rendering.setting_occupancy``); previews march the union grid."""

    def resolve_params(self, params: Mapping[str, float]) -> list[float]:
        """Parameter values in axis order; missing names take their default.

        Raises ValueError naming the problem for unknown names, non-finite values or values
        outside the training range.
        """
        known = {a.name for a in self.info.params}
        unknown = sorted(set(params) - known)
        if unknown:
            raise ValueError(f"unknown parameter(s) {unknown}; this scene has {sorted(known)}")
        values = []
        for axis in self.meta.param_axes:
            value = float(params.get(axis.name, axis.default))
            if not math.isfinite(value):
                raise ValueError(f"parameter {axis.name!r} must be finite, got {value}")
            if not axis.contains(value):
                raise ValueError(
                    f"parameter {axis.name!r}={value} is outside its range [{axis.min}, {axis.max}]"
                )
            values.append(min(max(value, axis.min), axis.max))
        return values

    def view(
        self,
        c2w: np.ndarray,
        fov_deg: float | None,
        width: int,
        height: int,
        params: Mapping[str, float] | None = None,
        quality: Quality = "full",
        view_height: float | None = None,
    ) -> FrameView:
        """The frame ``render`` takes, checked: ``c2w`` a 4x4 rigid camera-to-world matrix (OpenGL
        axes); ``fov_deg`` the horizontal field of view of a perspective camera, or ``view_height``
        (with ``fov_deg`` None) the world units an orthographic image spans vertically; parameters
        by name (missing ones take their default). ValueError names the first problem."""
        m = check_rigid_c2w(c2w)
        if (fov_deg is None) == (view_height is None):
            raise ValueError("give fov_deg (perspective) or view_height (orthographic), one of them")
        if fov_deg is not None and not (math.isfinite(fov_deg) and 0.0 < fov_deg < 180.0):
            raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg}")
        if view_height is not None and not (math.isfinite(view_height) and view_height > 0.0):
            raise ValueError(f"view_height must be a positive number of world units, got {view_height}")
        if width < 1 or height < 1:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        if quality not in ("preview", "full"):
            raise ValueError(f"quality must be 'preview' or 'full', got {quality!r}")
        values = tuple(self.resolve_params(params or {}))
        return FrameView(m, None if fov_deg is None else float(fov_deg),
                         None if view_height is None else float(view_height), int(width), int(height), values, quality)

    def _params(self, view: FrameView) -> torch.Tensor:
        """The view's parameters normalised, [k] on the scene's device."""
        normalized = [axis.normalize(v) for axis, v in zip(self.meta.param_axes, view.values, strict=True)]
        return torch.tensor(normalized, dtype=torch.float32, device=self.device)

    def setting_grid(self, view: FrameView) -> tuple[EmptySpace | None, GridBuild | None]:
        """(the occupancy grid of the view's parameter setting, or None: march the union grid; the
        build of that grid when one is due, for the caller to run or drop, or None). Full-quality
        frames only (``rendering.setting_occupancy``)."""
        settings = RenderSettings.from_meta(self.meta, view.quality, self.frames)
        if view.quality != "full" or not settings.use_occupancy:
            return None, None
        return self.setting_occupancy.lookup(self._params(view), self.field.voxel_size() * settings.step_ratio)

    def draw(self, view: FrameView, own: EmptySpace | None = None, cancel: CancelCheck | None = None) -> np.ndarray:
        """Render a checked frame: uint8 [height, width, 3]. ``own``: the grid of its setting
        (``setting_grid``), None for the union. ``preview`` renders at a fraction of the resolution
        with a longer step and upsamples. RenderCancelled once ``cancel`` answers True (asked
        between chunks of rays)."""
        settings = RenderSettings.from_meta(self.meta, view.quality, self.frames)
        intrinsics = (Intrinsics.from_fov(view.width, view.height, math.radians(view.fov_deg))
                      if view.fov_deg is not None
                      else Intrinsics.from_view_height(view.width, view.height, float(view.view_height)))  # type: ignore[arg-type]
        c2w_t = torch.as_tensor(view.c2w, dtype=torch.float32, device=self.device)
        try:
            with torch.inference_mode():
                params = self._params(view)
                rgb = render_image_scaled(self.field, c2w_t, intrinsics, params, settings, own, cancel)  # [h, w, 3]
                return (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
        finally:  # a frame stopped early allocated as much as a finished one
            if view.width * view.height >= TRIM_AFTER_PIXELS:
                release_free_memory()

    def render(
        self,
        c2w: np.ndarray,
        fov_deg: float | None,
        width: int,
        height: int,
        params: Mapping[str, float] | None = None,
        quality: Quality = "full",
        cancel: CancelCheck | None = None,
        view_height: float | None = None,
    ) -> np.ndarray:
        """``draw`` of ``view``: one frame, uint8 [height, width, 3]; ValueError for any invalid
        input (nothing is rendered then). A setting grid that falls due is built on the scene's own
        worker thread (``SettingOccupancy.run_own``)."""
        frame = self.view(c2w, fov_deg, width, height, params, quality, view_height)
        own, build = self.setting_grid(frame)
        if build is not None:
            own = self.setting_occupancy.run_own(build)
        return self.draw(frame, own, cancel)


def load_scene(path: str | Path, device: torch.device | None = None,
               frames: FramesConfig | None = None) -> SceneRenderer:
    """Load and fully validate a checkpoint; raises CheckpointError naming the problem. ``frames``:
    how this machine renders its frames (default ``FramesConfig()``)."""
    device = device or torch.device("cpu")
    field, meta = load_checkpoint(path, device)
    return SceneRenderer(field, meta, device, frames)
