"""Suite-wide settings: one torch thread (tests are small; extra threads only contend on 2 cores)."""

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def _single_thread():
    torch.set_num_threads(1)
    yield


@pytest.fixture(scope="session")
def synthetic_scene(tmp_path_factory):
    """``synthetic_scene(name, res)``: the folder of synthetic scene ``name`` rendered at ``res``
    pixels with a 2-view test path, made once per session (``visnerf make-scene``)."""
    import subprocess
    import sys

    root = tmp_path_factory.mktemp("synthetic_scenes")

    def make(name: str, res: int = 32):
        out = root / f"{name}_{res}"
        if not (out / "transforms_train.json").exists():
            subprocess.run([sys.executable, "-m", "visnerf.cli", "make-scene", name, "--out", str(out), "--res",
                            str(res), "--test-views", "2", "--quiet"], check=True, timeout=300)
        return out

    return make
