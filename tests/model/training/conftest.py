"""Small synthetic scenes rendered once per test session, for the recipe's choices."""

import subprocess
import sys
from pathlib import Path

import pytest

from visnerf.data.parsers.blender import load_dataset
from visnerf.data.scene import SceneData


def rendered(root: Path, name: str, res: int = 32) -> Path:
    out = root / f"{name}_{res}"
    if not (out / "transforms_train.json").exists():
        subprocess.run([sys.executable, "-m", "visnerf.cli", "make-scene", name, "--out", str(out), "--res", str(res),
                        "--test-views", "4", "--quiet"], check=True)
    return out


@pytest.fixture(scope="session")
def scene_root(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("recipe_scenes")


@pytest.fixture(scope="session")
def surface_data(scene_root) -> Path:
    """An opaque isosurface (``tangle_static``), K = 0: the dataset folder."""
    return rendered(scene_root, "tangle_static")


@pytest.fixture(scope="session")
def surface_scene(surface_data) -> SceneData:
    return load_dataset(surface_data, "train")


@pytest.fixture(scope="session")
def volume_scene(scene_root) -> SceneData:
    """Translucent volume rendering (``vortex_tf2``), K = 1."""
    return load_dataset(rendered(scene_root, "vortex_tf2"), "train")
