"""Uploads that cannot leave the server half changed: metadata defects refused with the field named
before anything is written, the answer built before the scene is committed, and the uploads and
deletions of one id run one at a time (two PUTs never both answer 201)."""

import json
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from safetensors import safe_open
from safetensors.torch import save_file
from server_helpers import AUTH, listing, scene_ids

import visnerf_server.routers.scenes as scenes_router
import visnerf_server.uploads as uploads


def edited_checkpoint(good: Path, path: Path, edit: Callable[[dict], None]) -> Path:
    """``good`` with its metadata document changed by ``edit`` (NaN and infinities written as
    Python's json writes them)."""
    with safe_open(str(good), "pt") as f:
        tensors = {k: f.get_tensor(k) for k in f.keys()}
        metadata = dict(f.metadata())
    document = json.loads(metadata["visnerf"])
    edit(document)
    metadata["visnerf"] = json.dumps(document)
    save_file(tensors, str(path), metadata=metadata)
    return path


DEFECTS: list[tuple[str, Callable[[dict], None], str]] = [
    ("nan-background", lambda d: d.update(background=[float("nan"), 1.0, 1.0]), "background[0] is NaN"),
    ("default-outside", lambda d: d["param_axes"][0].update(default=2.0), "param_axes[0].default 2.0 is outside [0, 1]"),
    ("reserved-name", lambda d: d["param_axes"][0].update(name="width"), "param_axes[0].name 'width'"),
    ("unknown-kind", lambda d: d.update(kind="hologram"), "kind must be one of dvr, ir"),
    ("huge-max-samples", lambda d: d["render"].update(max_samples=1e9), "render: max_samples must be a whole number"),
    ("zero-width", lambda d: d.update(image_width=0), "image_width must be a whole number in [1, 65536]"),
    ("infinite-distance", lambda d: d["camera"].update(distance=float("inf")), "camera.distance is Infinity"),
]


@pytest.mark.parametrize(("name", "edit", "detail"), DEFECTS, ids=[d[0] for d in DEFECTS])
@pytest.mark.parametrize("scene_id", ["fresh", "tiny"])
def test_metadata_defects_are_refused_and_change_nothing(
    shared, templates, tmp_path: Path, name: str, edit: Callable[[dict], None], detail: str, scene_id: str
) -> None:
    client, ckpt_dir = shared
    before_files = {p.name: p.read_bytes() for p in ckpt_dir.iterdir()}
    before_scenes = client.get("/api/scenes").json()
    bad = edited_checkpoint(templates["tiny"], tmp_path / f"{name}.safetensors", edit)
    response = client.put(f"/api/scenes/{scene_id}", content=bad.read_bytes(), headers=AUTH)
    assert response.status_code == 422, response.text
    assert detail in response.json()["detail"]
    assert {p.name: p.read_bytes() for p in ckpt_dir.iterdir()} == before_files
    assert client.get("/api/scenes").json() == before_scenes


def test_the_answer_is_built_before_the_scene_is_committed(
    client: TestClient, ckpt_dir: Path, templates, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Whatever fails while the answer is made fails before the swap: the scene is not there."""

    def broken(scene):
        raise RuntimeError("could not describe the scene")

    monkeypatch.setattr(scenes_router, "scene_detail", broken)
    plain = TestClient(client.app, raise_server_exceptions=False)  # the app of ``client``, its lifespan
    response = plain.put("/api/scenes/fresh", content=templates["still"].read_bytes(), headers=AUTH)
    assert response.status_code == 500
    assert listing(ckpt_dir) == ["tiny.safetensors", "two.safetensors"]
    assert scene_ids(client) == ["tiny", "two"]


class SlowValidation(threading.Event):
    """Set once a validation has begun; ``most_at_once``: the most validations that ran together."""

    def __init__(self) -> None:
        super().__init__()
        self.running = self.most_at_once = 0
        self.lock = threading.Lock()


@pytest.fixture
def slow_validation(monkeypatch: pytest.MonkeyPatch) -> SlowValidation:
    """Validation of an upload takes 0.3 s more, long enough for a second upload to arrive."""
    real = uploads.load_and_check
    seen = SlowValidation()

    def slow(path, device, frames):
        with seen.lock:
            seen.running += 1
            seen.most_at_once = max(seen.most_at_once, seen.running)
        seen.set()
        try:
            time.sleep(0.3)
            return real(path, device, frames)
        finally:
            with seen.lock:
                seen.running -= 1

    monkeypatch.setattr(uploads, "load_and_check", slow)
    return seen


def test_concurrent_uploads_of_one_id_never_both_create(client: TestClient, templates, slow_validation: SlowValidation) -> None:
    data = templates["still"].read_bytes()

    def put(scene_id: str):
        return client.put(f"/api/scenes/{scene_id}", content=data, headers=AUTH)

    for scene_id in ("race-a", "race-b"):
        with ThreadPoolExecutor(2) as pool:
            answers = list(pool.map(put, [scene_id, scene_id]))
        assert sorted(r.status_code for r in answers) == [200, 201], [r.text for r in answers]
        assert slow_validation.most_at_once == 1  # one after the other
        created = next(r for r in answers if r.status_code == 201)
        assert created.headers["location"] == f"/api/scenes/{scene_id}"
    assert scene_ids(client) == ["race-a", "race-b", "tiny", "two"]
    assert len(client.app.state.server.scene_locks) == 0  # no lock outlives its uploads


def test_a_delete_waits_for_the_upload_of_its_id(
    client: TestClient, ckpt_dir: Path, templates, slow_validation: SlowValidation
) -> None:
    with ThreadPoolExecutor(1) as pool:
        upload = pool.submit(client.put, "/api/scenes/fresh", content=templates["still"].read_bytes(), headers=AUTH)
        assert slow_validation.wait(10)
        deleted = client.delete("/api/scenes/fresh", headers=AUTH)  # waits, then finds the new scene
        assert upload.result(10).status_code == 201
    assert deleted.status_code == 204
    assert listing(ckpt_dir) == ["tiny.safetensors", "two.safetensors"]
    assert scene_ids(client) == ["tiny", "two"]
