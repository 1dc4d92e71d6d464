"""A loaded scene's setting as a bake (``baking.bake_setting`` with the scene's field and box)."""

from collections.abc import Mapping

import torch

from visnerf.bake.bake_file import Bake
from visnerf.bake.baking import BakeTarget, bake_setting
from visnerf.config.bake import BakeConfig
from visnerf.inference import SceneRenderer
from visnerf.rendering.render_settings import RenderSettings
from visnerf.representation.frame_field import FrameField


def bake_scene(scene: SceneRenderer, params: Mapping[str, float] | None = None, cfg: BakeConfig | None = None,
               checkpoint_hash: str = "") -> Bake:
    """The bake of ``scene`` at ``params`` (by name; missing ones take their default).
    ValueError names an unknown or out-of-range parameter."""
    values = scene.resolve_params(params or {})
    field, meta = scene.field, scene.meta
    normalized = torch.tensor([a.normalize(v) for a, v in zip(meta.param_axes, values, strict=True)],
                              dtype=torch.float32, device=scene.device)
    settings = RenderSettings.from_meta(meta, "full", scene.frames)
    with torch.inference_mode():
        q_density, q_appearance = field.param_features(normalized[None])
        source = FrameField(field, q_density, q_appearance, torch.float32)
        box = field.aabb.detach().cpu().double().tolist()  # type: ignore[operator]
        target = BakeTarget(
            aabb=(tuple(box[0]), tuple(box[1])),  # type: ignore[arg-type]
            model_grid=tuple(field.resolution),  # type: ignore[arg-type]
            step=field.voxel_size() * settings.step_ratio,
            occupancy_threshold=meta.render.occupancy_threshold,
            early_stop_eps=settings.early_stop_eps,
            union=field.occupancy,
            cosine_powers=tuple(field.cfg.level_cosine_powers),
            background=tuple(float(v) for v in meta.background),  # type: ignore[arg-type]
            kind=meta.kind,
            title=meta.title,
            params={a.name: float(v) for a, v in zip(meta.param_axes, values, strict=True)},
            source={"checkpoint": checkpoint_hash} if checkpoint_hash else {},
        )
        return bake_setting(source, target, cfg)
