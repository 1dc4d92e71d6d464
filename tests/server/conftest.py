"""Fixtures for the server tests: tiny random checkpoints in a temporary folder, an app built by
``create_app(settings)`` and a ``TestClient`` that runs its lifespan."""

import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from server_helpers import make_settings

from visnerf.testing import make_tiny_checkpoint
from visnerf_server.app import create_app
from visnerf_server.settings import Settings


@pytest.fixture(autouse=True)
def _clean_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """Settings read ``VISNERF_*`` variables; the tests must not see the developer's."""
    for name in list(os.environ):
        if name.startswith("VISNERF_"):
            monkeypatch.delenv(name)


@pytest.fixture(scope="session")
def templates(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Good checkpoints, written once: ``tiny`` (axis a in [0, 1]), ``two`` (t in [0, 2], iso in
    [0.1, 0.5], kind ir), ``still`` (no parameters), ``other`` (like tiny, another seed)."""
    folder = tmp_path_factory.mktemp("templates")
    return {
        "tiny": make_tiny_checkpoint(folder / "tiny.safetensors"),
        "two": make_tiny_checkpoint(
            folder / "two.safetensors", [("t", [0.0, 1.0, 2.0]), ("iso", [0.1, 0.5])], kind="ir", title="Two"
        ),
        "still": make_tiny_checkpoint(folder / "still.safetensors", [], title="Still"),
        "other": make_tiny_checkpoint(folder / "other.safetensors", seed=7, title="Other"),
    }


@pytest.fixture
def ckpt_dir(tmp_path: Path, templates: dict[str, Path]) -> Path:
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    for name in ("tiny", "two"):
        shutil.copy(templates[name], folder / f"{name}.safetensors")
    return folder


@pytest.fixture
def settings(ckpt_dir: Path, tmp_path: Path) -> Settings:
    return make_settings(ckpt_dir, tmp_path / "state")


@pytest.fixture
def client(settings: Settings) -> Iterator[TestClient]:
    with TestClient(create_app(settings)) as test_client:
        yield test_client


@pytest.fixture(scope="module")
def shared(
    tmp_path_factory: pytest.TempPathFactory, templates: dict[str, Path]
) -> Iterator[tuple[TestClient, Path]]:
    """One app per test module, for tests that must leave the scenes, the folder and the cache as
    they found them (bad requests, refused uploads): (client, checkpoints folder)."""
    root = tmp_path_factory.mktemp("shared")
    folder = root / "checkpoints"
    folder.mkdir()
    for name in ("tiny", "two"):
        shutil.copy(templates[name], folder / f"{name}.safetensors")
    with pytest.MonkeyPatch.context() as patch:
        for name in list(os.environ):
            if name.startswith("VISNERF_"):
                patch.delenv(name)
        app = create_app(make_settings(folder, root / "state"))
    with TestClient(app) as test_client:
        yield test_client, folder
