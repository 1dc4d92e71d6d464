"""Small synthetic scenes for the recipe's choices."""

from pathlib import Path

import pytest

from visnerf.data.datasets import load_dataset
from visnerf.data.scene import SceneData


@pytest.fixture(scope="session")
def surface_data(synthetic_scene) -> Path:
    """An opaque isosurface (``tangle_static``), K = 0: the dataset folder."""
    return synthetic_scene("tangle_static")


@pytest.fixture(scope="session")
def surface_scene(surface_data) -> SceneData:
    return load_dataset(surface_data, "train")


@pytest.fixture(scope="session")
def volume_scene(synthetic_scene) -> SceneData:
    """Translucent volume rendering (``vortex_tf2``), K = 1."""
    return load_dataset(synthetic_scene("vortex_tf2"), "train")



@pytest.fixture(scope="session")
def iso_sweep_scene(synthetic_scene) -> SceneData:
    """Opaque isosurfaces at five isovalues (``tangle_iso``), K = 1: nested surfaces."""
    return load_dataset(synthetic_scene("tangle_iso"), "train")
