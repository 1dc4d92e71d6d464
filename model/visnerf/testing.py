"""Small helpers for tests and demos: a tiny, valid, randomly initialised checkpoint."""

from pathlib import Path

import torch

from visnerf.checkpoint import CheckpointMeta, ParamAxis, save_checkpoint
from visnerf.config import FieldConfig, RenderConfig
from visnerf.representation.field import VisNerfField


def make_tiny_field(
    param_axes: list[tuple[str, list[float]]], seed: int = 0, resolution: int = 8
) -> tuple[VisNerfField, tuple[ParamAxis, ...]]:
    """A small random field whose density is high enough to show something."""
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
        )
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
) -> Path:
    """Write a small valid checkpoint (about 50 kB) with the given parameter axes."""
    axes_spec = [("a", [0.0, 1.0])] if param_axes is None else param_axes
    field, axes = make_tiny_field(axes_spec, seed)
    meta = CheckpointMeta(
        field=field.cfg,
        render=RenderConfig(step_ratio=0.5),
        param_axes=axes,
        bbox=((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5)),
        camera={"azimuth": 30.0, "elevation": 20.0, "distance": 2.5, "fov_deg": 30.0},
        image_width=64,
        image_height=64,
        title=title,
        kind=kind,
        provenance={"dataset": "random", "iterations": 0, "train_seconds": 0.0, "val_psnr": None},
    )
    return save_checkpoint(field, meta, path)
