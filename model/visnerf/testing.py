"""Small helpers for tests and demos: a tiny, valid, randomly initialised checkpoint."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import torch

from visnerf.checkpoint import CheckpointMeta, ParamAxis, save_checkpoint
from visnerf.config import FieldConfig, RenderConfig
from visnerf.data.cameras import Intrinsics, orbit_c2w
from visnerf.data.scene import SceneData, axes_from_values
from visnerf.provenance import Provenance
from visnerf.representation.field import VisNerfField


def make_tiny_field(
    param_axes: list[tuple[str, list[float]]], seed: int = 0, resolution: int = 8, **field_options: object
) -> tuple[VisNerfField, tuple[ParamAxis, ...]]:
    """A small random field whose density is high enough to show something (``field_options``
    override its ``FieldConfig``)."""
    generator_state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    try:
        cfg = FieldConfig(
            resolution=(resolution,) * 3,
            n_density_components=4,
            n_appearance_components=8,
            param_lengths=tuple(len(v) for _, v in param_axes),
            hidden_width=16,
            density_shift=0.0,
            init_scale=0.5,
            factor_storage="float16",
        )
        cfg = dataclasses.replace(cfg, **field_options)  # type: ignore[arg-type]
        field = VisNerfField(cfg, torch.tensor([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]]))
        axes = []
        knots = []
        for name, values in param_axes:
            vals = sorted(float(v) for v in values)
            lo, hi = vals[0], vals[-1]
            axis = ParamAxis(name, lo, hi, tuple(vals), vals[len(vals) // 2])
            axes.append(axis)
            knots.append(torch.tensor([axis.normalize(v) for v in vals]))
            with torch.no_grad():  # make the parameters matter, so renders differ along each axis
                for table in (*field.density_params.tables, *field.appearance_params.tables):
                    table.copy_(1.0 + 0.9 * torch.randn_like(table))
        if field.levels is not None:  # increasing levels: surfaces that shrink as the value grows
            with torch.no_grad():
                field.levels.table.copy_(torch.linspace(-1.0, 1.0, field.levels.table.shape[0])[:, None])
        field.set_param_knots(knots)
    finally:
        torch.random.set_rng_state(generator_state)
    return field, tuple(axes)


def make_tiny_checkpoint(
    path: str | Path,
    param_axes: list[tuple[str, list[float]]] | None = None,
    kind: str = "dvr",
    title: str = "Tiny",
    seed: int = 0,
    camera: dict[str, float] | None = None,
    **field_options: object,
) -> Path:
    """Write a small valid checkpoint (about 50 kB) with the given parameter axes (and default
    camera: ``view_height`` in place of ``fov_deg`` for a scene of orthographic images)."""
    axes_spec = [("a", [0.0, 1.0])] if param_axes is None else param_axes
    field, axes = make_tiny_field(axes_spec, seed, **field_options)
    meta = CheckpointMeta(
        field=field.cfg,
        render=RenderConfig(step_ratio=0.5),
        param_axes=axes,
        bbox=((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5)),
        camera=camera or {"azimuth": 30.0, "elevation": 20.0, "distance": 2.5, "fov_deg": 30.0},
        image_width=64,
        image_height=64,
        title=title,
        kind=kind,
        provenance=Provenance(dataset="random"),
    )
    return save_checkpoint(field, meta, path)


def make_noise_scene(n_views: int = 6, size: int = 16, n_values: int = 2) -> SceneData:
    """``n_views`` orbit views of random pixels at settings of one parameter ``t`` taking the
    values 0, 1, ..., ``n_values - 1`` in turn."""
    g = torch.Generator().manual_seed(0)
    values = np.array([[float(i % n_values)] for i in range(n_views)])
    _, axes = axes_from_values(["t"], values)
    c2w = torch.stack([torch.from_numpy(orbit_c2w(360.0 / n_views * i, 20.0, 2.0)).float() for i in range(n_views)])
    return SceneData(
        images=torch.randint(0, 256, (n_views, size, size, 3), generator=g, dtype=torch.uint8),
        c2w=c2w,
        intrinsics=Intrinsics.from_fov(size, size, math.radians(40.0)),
        params=torch.from_numpy(values).float(),
        param_axes=axes,
        view_ids=torch.arange(n_views),
        bbox=torch.tensor([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]]),
    )
