"""Typed configuration of the field, the renderer, the trainer, the recipe, the hold-out and the
machine's frames: one home for every
setting. The command line is generated from it (``config_options``), the checkpoint stores it whole,
benchmarks build from it; configurations are never mutated."""

from visnerf.config.checks import config_from_dict
from visnerf.config.field import FACTOR_STORAGE_DTYPES, FactorStorage, FieldConfig
from visnerf.config.frames import FramesConfig
from visnerf.config.holdout import HoldoutConfig
from visnerf.config.recipe import RECIPE, RecipeConfig, SurfaceRecipe
from visnerf.config.render import RenderConfig
from visnerf.config.train import DEFAULT_ITERATIONS, TrainConfig

__all__ = ["DEFAULT_ITERATIONS", "FACTOR_STORAGE_DTYPES", "FactorStorage", "FieldConfig", "FramesConfig",
           "HoldoutConfig", "RECIPE", "RecipeConfig", "RenderConfig", "SurfaceRecipe", "TrainConfig",
           "config_from_dict"]
