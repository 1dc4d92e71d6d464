"""The store watcher (``store_watch``): servers sharing one checkpoints folder see each other's
uploads and deletions, never half a file, and name a bad file in readiness without serving it.
Most tests drive ``StoreWatcher.poll`` by hand (apps built with ``store_poll_s=0``); the last ones
run the watcher's thread."""

import os
import shutil
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from server_helpers import AUTH, make_settings, scene_ids

from visnerf_server.app import create_app
from visnerf_server.dependencies import ServerState
from visnerf_server.registry import file_digest
from visnerf_server.store_watch import StoreWatcher


def server_of(client: TestClient) -> ServerState:
    return client.app.state.server  # type: ignore[attr-defined]


def watcher_of(client: TestClient) -> StoreWatcher:
    return StoreWatcher(server_of(client), threading.Event())


def put_in_place(source: Path, target: Path) -> None:
    """What an upload does: a hidden temporary in the folder, renamed over the target."""
    tmp = target.parent / f".upload-test{time.monotonic_ns()}.tmp"
    shutil.copy(source, tmp)
    os.replace(tmp, target)


def version(client: TestClient, scene_id: str) -> str | None:
    response = client.get(f"/api/scenes/{scene_id}")
    return response.json()["version"] if response.status_code == 200 else None


@pytest.fixture
def apps(ckpt_dir: Path, tmp_path: Path) -> Iterator[list[TestClient]]:
    """Two servers on one folder (two replicas), their watchers driven by hand."""
    with ExitStack() as stack:
        yield [
            stack.enter_context(
                TestClient(create_app(make_settings(ckpt_dir, tmp_path / f"state{i}", store_poll_s=0.0)))
            )
            for i in range(2)
        ]


def test_a_new_file_is_served_once_it_has_settled(apps: list[TestClient], ckpt_dir: Path, templates) -> None:
    client = apps[0]
    watcher = watcher_of(client)
    watcher.poll()  # the start-up scenes: nothing to load
    put_in_place(templates["other"], ckpt_dir / "new.safetensors")
    for _ in range(2):  # not listed yet, then seen once (it may still be growing)
        waiting = client.get("/api/scenes/new")
        assert waiting.status_code == 503 and waiting.headers["retry-after"] == "1"  # a proxy tries another replica
        watcher.poll()
    watcher.poll()  # the same size, mtime and inode a poll later: read, checked, installed
    assert version(client, "new") == file_digest(ckpt_dir / "new.safetensors")[:16]
    assert client.get("/api/scenes/new/render?width=8&height=8").status_code == 200
    assert client.get("/api/ready").json() == {"ready": True, "scenes": 3, "failed": {}}


def test_a_file_written_in_place_is_never_half_installed(apps: list[TestClient], ckpt_dir: Path, templates) -> None:
    client = apps[0]
    watcher = watcher_of(client)
    data = templates["other"].read_bytes()
    target = ckpt_dir / "copied.safetensors"
    target.write_bytes(data[: len(data) // 3])
    watcher.poll()
    target.write_bytes(data[: 2 * len(data) // 3])  # still growing at the next poll: not read
    watcher.poll()
    assert client.get("/api/ready").json()["failed"] == {}
    watcher.poll()  # stalled for a whole poll: read, refused, named in readiness, not served
    assert "copied" in client.get("/api/ready").json()["failed"]
    assert client.get("/api/scenes/copied").status_code == 404  # bad: not on its way
    assert scene_ids(client) == ["tiny", "two"]
    watcher.poll()  # not tried again while it stays the same
    target.write_bytes(data)
    watcher.poll()
    watcher.poll()
    assert version(client, "copied") == file_digest(target)[:16]
    assert client.get("/api/ready").json()["failed"] == {}


def test_upload_temporaries_and_other_names_are_ignored(apps: list[TestClient], ckpt_dir: Path, templates) -> None:
    client = apps[0]
    watcher = watcher_of(client)
    (ckpt_dir / ".upload-abc123.tmp").write_bytes(templates["other"].read_bytes()[:100])
    shutil.copy(templates["other"], ckpt_dir / ".hidden.safetensors")
    shutil.copy(templates["other"], ckpt_dir / "notes.txt")
    for _ in range(3):
        watcher.poll()
    assert scene_ids(client) == ["tiny", "two"]
    assert client.get("/api/ready").json()["failed"] == {}


def test_replaced_and_removed_files(apps: list[TestClient], ckpt_dir: Path, templates) -> None:
    client = apps[0]
    server = server_of(client)
    watcher = watcher_of(client)
    watcher.poll()
    tiny = server.registry.get("tiny")
    os.utime(ckpt_dir / "tiny.safetensors")  # touched, same bytes: not loaded again
    watcher.poll()
    watcher.poll()
    assert server.registry.get("tiny") is tiny
    put_in_place(templates["other"], ckpt_dir / "tiny.safetensors")
    watcher.poll()
    assert server.registry.get("tiny") is tiny  # the old one is served until the new one is checked
    watcher.poll()
    assert version(client, "tiny") == file_digest(templates["other"])[:16]
    (ckpt_dir / "tiny.safetensors").unlink()
    watcher.poll()
    assert client.get("/api/scenes/tiny").status_code == 404
    assert scene_ids(client) == ["two"]


def test_a_bad_replacement_is_reported_and_not_served(apps: list[TestClient], ckpt_dir: Path) -> None:
    client = apps[0]
    watcher = watcher_of(client)
    watcher.poll()
    put_in_place_bytes = ckpt_dir / ".upload-bad.tmp"
    put_in_place_bytes.write_bytes(b"not a checkpoint")
    os.replace(put_in_place_bytes, ckpt_dir / "two.safetensors")
    watcher.poll()
    watcher.poll()
    ready = client.get("/api/ready").json()
    assert ready["ready"] is True and list(ready["failed"]) == ["two"]
    assert str(ckpt_dir) not in ready["failed"]["two"]
    assert scene_ids(client) == ["tiny"]  # as a server started now would serve
    (ckpt_dir / "two.safetensors").unlink()
    watcher.poll()
    assert client.get("/api/ready").json()["failed"] == {}


def test_an_unreadable_folder_is_not_an_empty_store(apps: list[TestClient], ckpt_dir: Path) -> None:
    client = apps[0]
    watcher = watcher_of(client)
    watcher.poll()
    ckpt_dir.rename(ckpt_dir.with_name("unmounted"))
    try:
        watcher.poll()
        assert scene_ids(client) == ["tiny", "two"]
    finally:
        ckpt_dir.with_name("unmounted").rename(ckpt_dir)


def test_uploads_and_deletes_reach_the_other_replica(
    apps: list[TestClient], ckpt_dir: Path, tmp_path: Path, templates
) -> None:
    first, second = apps
    watchers = [watcher_of(first), watcher_of(second)]
    uploaded = first.put("/api/scenes/shared", content=templates["other"].read_bytes(), headers=AUTH)
    assert uploaded.status_code == 201
    own = server_of(first).registry.get("shared")
    for watcher in watchers:
        watcher.poll()
        watcher.poll()
    assert server_of(first).registry.get("shared") is own  # its own upload is not loaded again
    assert version(second, "shared") == uploaded.json()["version"]
    assert second.delete("/api/scenes/tiny", headers=AUTH).status_code == 204
    watchers[0].poll()
    assert scene_ids(first) == scene_ids(second) == ["shared", "two"]
    # A replica started later serves the same.
    with TestClient(create_app(make_settings(ckpt_dir, tmp_path / "state-late", store_poll_s=0.0))) as late:
        assert scene_ids(late) == ["shared", "two"]
        assert version(late, "shared") == uploaded.json()["version"]


def test_concurrent_uploads_of_one_id_on_two_replicas(apps: list[TestClient], ckpt_dir: Path, templates) -> None:
    bodies = [templates["other"].read_bytes(), templates["still"].read_bytes()]
    answers: list[int] = []
    barrier = threading.Barrier(2)

    def upload(client: TestClient, body: bytes) -> None:
        barrier.wait()
        answers.append(client.put("/api/scenes/race", content=body, headers=AUTH).status_code)

    threads = [threading.Thread(target=upload, args=pair) for pair in zip(apps, bodies, strict=True)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert sorted(answers) in ([200, 201], [201, 201])  # each saw no file, or the other's
    on_disk = (ckpt_dir / "race.safetensors").read_bytes()
    assert on_disk in bodies  # the last complete rename, never a mix
    assert not list(ckpt_dir.glob(".upload-*"))
    for client in apps:
        watcher = watcher_of(client)
        watcher.poll()
        watcher.poll()
    winner = file_digest(ckpt_dir / "race.safetensors")[:16]
    assert version(apps[0], "race") == version(apps[1], "race") == winner


def wait_until(condition, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline
        time.sleep(0.02)


def watcher_threads() -> set[threading.Thread]:
    return {t for t in threading.enumerate() if t.name == "visnerf-store-watcher"}


def test_the_watcher_thread_follows_the_folder(ckpt_dir: Path, tmp_path: Path, templates) -> None:
    settings = make_settings(ckpt_dir, tmp_path / "state", store_poll_s=0.05)
    before = watcher_threads()
    with TestClient(create_app(settings)) as client:
        started = watcher_threads() - before
        assert len(started) == 1
        put_in_place(templates["still"], ckpt_dir / "added.safetensors")
        wait_until(lambda: "added" in scene_ids(client))
        assert client.get("/api/scenes/added").json()["title"] == "Still"
        (ckpt_dir / "tiny.safetensors").unlink()
        wait_until(lambda: "tiny" not in scene_ids(client))
    assert not any(t.is_alive() for t in started)  # joined at shutdown


def test_store_poll_zero_turns_the_watcher_off(ckpt_dir: Path, tmp_path: Path, templates) -> None:
    before = watcher_threads()
    with TestClient(create_app(make_settings(ckpt_dir, tmp_path / "state", store_poll_s=0.0))) as client:
        assert watcher_threads() == before
        put_in_place(templates["still"], ckpt_dir / "added.safetensors")
        time.sleep(0.2)
        assert scene_ids(client) == ["tiny", "two"]
