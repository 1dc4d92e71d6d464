"""The in-memory dataset: uint8 pixels, cameras and parameter values, whatever the source format."""

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from jaxtyping import Float, Int, UInt8
from torch import Tensor

from visnerf.checkpoint import ParamAxis
from visnerf.data.cameras import Intrinsics, orbit_from_c2w


@dataclass(frozen=True)
class SceneData:
    """Frames of one dataset split. Pixels stay uint8; rays are made per batch."""

    images: UInt8[Tensor, "n h w 3"]
    """RGB, composited on ``background``."""
    c2w: Float[Tensor, "n 4 4"]
    """Camera-to-world matrices, OpenGL axes."""
    intrinsics: Intrinsics
    params: Float[Tensor, "n k"]
    """Raw parameter values of the axes that vary (constant ones dropped)."""
    param_axes: tuple[ParamAxis, ...]
    view_ids: Int[Tensor, " n"]
    """Index of each frame's camera among the distinct camera poses, in order of appearance."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    bbox: Float[Tensor, "2 3"] | None = None
    """Content box from the dataset, if it gives one."""
    title: str = ""
    kind: str = "dvr"
    file_paths: tuple[str, ...] = field(default_factory=tuple)
    source: str = ""
    depths: Float[Tensor, "n h w"] | None = None
    """Depth along each pixel's ray where the source records it (pycinema ``.h5``), NaN where it hit nothing."""

    @property
    def n_frames(self) -> int:
        return int(self.images.shape[0])

    @property
    def n_params(self) -> int:
        return len(self.param_axes)

    def normalized_params(self) -> Float[Tensor, "n k"]:
        """Parameters mapped to [-1, 1] by each axis's training range."""
        cols = [
            torch.tensor([a.normalize(float(v)) for v in self.params[:, k]], dtype=torch.float32)
            for k, a in enumerate(self.param_axes)
        ]
        return torch.stack(cols, dim=-1) if cols else torch.zeros(self.n_frames, 0)

    def knots(self) -> list[Tensor]:
        """Normalised training values of each axis."""
        return [torch.tensor([a.normalize(v) for v in a.values], dtype=torch.float32) for a in self.param_axes]

    def subset(self, indices: Tensor) -> "SceneData":
        """Frames at ``indices``; axes and metadata unchanged."""
        idx = indices.long()
        return SceneData(
            images=self.images[idx],
            c2w=self.c2w[idx],
            intrinsics=self.intrinsics,
            params=self.params[idx],
            param_axes=self.param_axes,
            view_ids=self.view_ids[idx],
            background=self.background,
            bbox=self.bbox,
            title=self.title,
            kind=self.kind,
            file_paths=tuple(self.file_paths[i] for i in idx.tolist()) if self.file_paths else (),
            source=self.source,
            depths=None if self.depths is None else self.depths[idx],
        )

    def default_camera(self) -> dict[str, float]:
        """Orbit camera of the first frame, with the dataset's field of view, or its view height
        for an orthographic dataset (the key ``view_height`` marks a parallel projection)."""
        az, el, dist = orbit_from_c2w(self.c2w[0].double().numpy())
        lens = ({"view_height": self.intrinsics.view_height} if self.intrinsics.orthographic
                else {"fov_deg": self.intrinsics.fov_x_deg})
        return {"azimuth": az, "elevation": el, "distance": dist, **lens}


def axes_from_values(names: list[str], values: np.ndarray) -> tuple[list[int], tuple[ParamAxis, ...]]:
    """Axes that vary across ``values`` [n, k]: their column indices and descriptions."""
    keep, axes = [], []
    for k, name in enumerate(names):
        distinct = np.unique(values[:, k])
        if distinct.size < 2:
            continue  # a parameter that never varies carries no information
        keep.append(k)
        default = float(distinct[(distinct.size - 1) // 2])
        axes.append(ParamAxis(name, float(distinct[0]), float(distinct[-1]), tuple(float(v) for v in distinct),
                              default))
    return keep, tuple(axes)


def view_ids_from_poses(c2w: np.ndarray, decimals: int = 3) -> np.ndarray:
    """Group frames by camera position: frames sharing a position share a view id."""
    keys = np.round(c2w[:, :3, 3], decimals)
    ids: dict[tuple[float, ...], int] = {}
    return np.array([ids.setdefault(tuple(k.tolist()), len(ids)) for k in keys], dtype=np.int64)


def estimate_bbox(scene: SceneData, margin: float = 1.2) -> torch.Tensor:
    """A cube around the origin that every camera sees whole: the dataset's bbox if it has one."""
    if scene.bbox is not None:
        return scene.bbox.clone()
    k = scene.intrinsics
    half_view = 0.5 * min(k.width / k.fx, k.height / k.fy)  # a pinhole's tangent, an orthographic view's half size
    if k.orthographic:
        r = margin * half_view
        return torch.tensor([[-r, -r, -r], [r, r, r]], dtype=torch.float32)
    dist = float(torch.linalg.norm(scene.c2w[:, :3, 3], dim=-1).min())
    r = margin * dist * math.sin(math.atan(half_view))
    return torch.tensor([[-r, -r, -r], [r, r, r]], dtype=torch.float32)
