"""Uploads (PUT) and deletion (DELETE): token checks, full validation, atomic swap, nothing left
behind on any failure."""

import asyncio
import os
import stat
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from server_helpers import (
    AUTH,
    ORBIT,
    TOKEN,
    image_size,
    listing,
    make_settings,
    nan_checkpoint,
    pickle_checkpoint,
    scene_ids,
    truncated_checkpoint,
    wrong_shape_checkpoint,
)

from visnerf_server.app import create_app

SMALL = {"camera": ORBIT, "width": 16, "height": 16}


def test_upload_new_scene_is_live_without_restart(client: TestClient, ckpt_dir: Path, templates) -> None:
    response = client.put("/api/scenes/fresh", content=templates["still"].read_bytes(), headers=AUTH)
    assert response.status_code == 201, response.text
    assert response.headers["location"] == "/api/scenes/fresh"
    body = response.json()
    assert body["id"] == "fresh" and body["title"] == "Still" and body["params"] == []
    assert listing(ckpt_dir) == ["fresh.safetensors", "tiny.safetensors", "two.safetensors"]
    assert (ckpt_dir / "fresh.safetensors").read_bytes() == templates["still"].read_bytes()
    assert scene_ids(client) == ["fresh", "tiny", "two"]
    render = client.post("/api/scenes/fresh/render", json=SMALL)
    assert render.status_code == 200
    assert image_size(render.content) == ("PNG", 16, 16)


def test_replace_scene_is_200_and_drops_stale_frames(client: TestClient, ckpt_dir: Path, templates) -> None:
    before = client.post("/api/scenes/tiny/render", json=SMALL)
    version = client.get("/api/scenes/tiny").json()["version"]
    response = client.put("/api/scenes/tiny", content=templates["other"].read_bytes(), headers=AUTH)
    assert response.status_code == 200
    assert response.json()["title"] == "Other"
    assert response.json()["version"] != version
    after = client.post("/api/scenes/tiny/render", json=SMALL)
    assert after.headers["x-cache"] == "miss"
    assert after.content != before.content
    assert listing(ckpt_dir) == ["tiny.safetensors", "two.safetensors"]


def test_delete_scene(client: TestClient, ckpt_dir: Path) -> None:
    response = client.delete("/api/scenes/two", headers=AUTH)
    assert response.status_code == 204
    assert response.content == b""
    assert listing(ckpt_dir) == ["tiny.safetensors"]
    assert scene_ids(client) == ["tiny"]
    assert client.get("/api/scenes/two").status_code == 404
    assert client.post("/api/scenes/two/render", json=SMALL).status_code == 404
    again = client.delete("/api/scenes/two", headers=AUTH)
    assert again.status_code == 404
    assert again.json() == {"detail": "unknown scene 'two'"}


@pytest.mark.parametrize(
    ("headers", "status", "detail"),
    [
        ({}, 401, "missing Authorization"),
        ({"Authorization": "Basic dXNlcjpwYXNz"}, 401, "Bearer"),
        ({"Authorization": "Bearer"}, 401, "Bearer"),
        ({"Authorization": "Bearer wrong-token"}, 403, "wrong token"),
        ({"Authorization": f"Bearer {TOKEN}x"}, 403, "wrong token"),
        ({"Authorization": "Bearer t\u00e9st".encode("latin-1")}, 403, "wrong token"),
    ],
)
def test_token_is_required(shared, templates, headers: dict, status: int, detail: str) -> None:
    client, ckpt_dir = shared
    before = listing(ckpt_dir)
    put = client.put("/api/scenes/fresh", content=templates["tiny"].read_bytes(), headers=headers)
    delete = client.delete("/api/scenes/tiny", headers=headers)
    for response in (put, delete):
        assert response.status_code == status
        assert detail in response.json()["detail"]
    if status == 401:
        assert put.headers["www-authenticate"] == "Bearer"
    assert listing(ckpt_dir) == before
    assert scene_ids(client) == ["tiny", "two"]


def _bad_file(kind: str, templates: dict[str, Path], tmp_path: Path) -> Path:
    good = templates["tiny"]
    path = tmp_path / f"bad-{kind}.safetensors"
    if kind == "pickle":
        return pickle_checkpoint(path)
    if kind == "truncated":
        return truncated_checkpoint(good, path)
    if kind == "shapes":
        return wrong_shape_checkpoint(good, path)
    if kind == "nan":
        return nan_checkpoint(good, path)
    if kind == "empty":
        path.write_bytes(b"")
        return path
    if kind == "text":
        path.write_text("hello")
        return path
    raise AssertionError(kind)


@pytest.mark.parametrize(
    ("kind", "detail"),
    [
        ("pickle", "not a safetensors file"),
        ("truncated", "invalid checkpoint"),
        ("shapes", "has shape [4, 9, 9]"),
        ("nan", "non-finite"),
        ("empty", "empty body"),
        ("text", "invalid checkpoint"),
    ],
)
@pytest.mark.parametrize("scene_id", ["fresh", "tiny"])
def test_invalid_checkpoints_are_refused_and_leave_nothing(
    shared, templates, tmp_path: Path, kind: str, detail: str, scene_id: str
) -> None:
    client, ckpt_dir = shared
    before_files = {p.name: p.read_bytes() for p in ckpt_dir.iterdir()}
    before_scenes = client.get("/api/scenes").json()
    bad = _bad_file(kind, templates, tmp_path)
    response = client.put(f"/api/scenes/{scene_id}", content=bad.read_bytes(), headers=AUTH)
    assert response.status_code == 422, response.text
    assert detail in response.json()["detail"]
    assert {p.name: p.read_bytes() for p in ckpt_dir.iterdir()} == before_files
    assert client.get("/api/scenes").json() == before_scenes
    assert client.post("/api/scenes/tiny/render", json=SMALL).status_code == 200


@pytest.mark.parametrize(
    "path",
    [
        "/api/scenes/..%2F..%2Fevil",
        "/api/scenes/%2e%2e",
        "/api/scenes/.hidden",
        "/api/scenes/Upper",
        "/api/scenes/a%20b",
        "/api/scenes/-dash",
        "/api/scenes/" + "x" * 65,
        "/api/scenes/tiny.safetensors",
        "/api/scenes/%00",
    ],
)
def test_path_traversal_and_bad_ids_are_refused(shared, templates, path: str) -> None:
    client, ckpt_dir = shared
    parent = listing(ckpt_dir.parent)
    before = listing(ckpt_dir)
    response = client.put(path, content=templates["tiny"].read_bytes(), headers=AUTH)
    assert response.status_code in (404, 405, 422), response.text
    assert "detail" in response.json()
    delete = client.delete(path, headers=AUTH)
    assert delete.status_code in (404, 405, 422)
    assert listing(ckpt_dir) == before
    assert listing(ckpt_dir.parent) == parent
    assert scene_ids(client) == ["tiny", "two"]


def test_oversize_upload_is_413(ckpt_dir: Path, tmp_path: Path, templates) -> None:
    settings = make_settings(ckpt_dir, tmp_path / "state", max_upload_bytes=4096)
    data = templates["tiny"].read_bytes()
    assert len(data) > 4096
    before = listing(ckpt_dir)
    with TestClient(create_app(settings)) as client:
        declared = client.put("/api/scenes/big", content=data, headers=AUTH)
        assert declared.status_code == 413
        assert "upload limit of 4096 bytes" in declared.json()["detail"]

        def chunks():  # no Content-Length: only the streaming check can catch it
            for i in range(0, len(data), 1000):
                yield data[i : i + 1000]

        streamed = client.put("/api/scenes/big", content=chunks(), headers=AUTH)
        assert streamed.status_code == 413
        assert "upload limit of 4096 bytes" in streamed.json()["detail"]
        assert scene_ids(client) == ["tiny", "two"]
    assert listing(ckpt_dir) == before


def test_upload_limit_is_checked_while_streaming(client: TestClient, ckpt_dir: Path) -> None:
    """Drive the ASGI app with an endless body: the server stops reading right after the limit."""
    app = client.app
    limit = app.state.server.settings.max_upload_bytes
    chunk = b"\0" * (1 << 20)
    consumed = 0
    messages: list[dict] = []

    async def receive() -> dict:
        nonlocal consumed
        consumed += 1
        if consumed > 4 * limit // len(chunk):
            raise AssertionError("server kept reading past the limit")
        return {"type": "http.request", "body": chunk, "more_body": True}

    async def send(message: dict) -> None:
        messages.append(message)

    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": "PUT",
        "scheme": "http",
        "path": "/api/scenes/endless",
        "raw_path": b"/api/scenes/endless",
        "query_string": b"",
        "root_path": "",
        "headers": [(b"host", b"testserver"), (b"authorization", f"Bearer {TOKEN}".encode())],
        "client": ("127.0.0.1", 5000),
        "server": ("testserver", 80),
    }
    before = listing(ckpt_dir)
    # A fresh thread has no event loop, even when another test (Playwright's sync API) left one here.
    import concurrent.futures

    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        pool.submit(asyncio.run, app(scope, receive, send)).result()
    assert messages[0]["type"] == "http.response.start" and messages[0]["status"] == 413
    assert consumed == limit // len(chunk) + 1
    assert listing(ckpt_dir) == before


def test_generated_token_file(ckpt_dir: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    state = tmp_path / "state"
    settings = make_settings(ckpt_dir, state, token=None)
    caplog.set_level("DEBUG")
    with TestClient(create_app(settings)) as client:
        token_file = state / "token"
        assert token_file.is_file()
        assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
        token = token_file.read_text().strip()
        assert len(token) >= 32
        assert client.delete("/api/scenes/nope", headers={"Authorization": "Bearer nope"}).status_code == 403
        assert (
            client.delete("/api/scenes/nope", headers={"Authorization": f"Bearer {token}"}).status_code == 404
        )
    assert str(token_file) in caplog.text
    assert token not in caplog.text  # the path is logged, never the token
    with TestClient(create_app(settings)) as client:  # reused on the next start
        assert token_file.read_text().strip() == token
        assert (
            client.delete("/api/scenes/nope", headers={"Authorization": f"Bearer {token}"}).status_code == 404
        )


def test_token_from_file_and_environment(
    ckpt_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    token_file = tmp_path / "secret"
    token_file.write_text("from-a-file\n")
    settings = make_settings(ckpt_dir, tmp_path / "state", token=None, token_file=token_file)
    with TestClient(create_app(settings)) as client:
        assert (
            client.delete("/api/scenes/nope", headers={"Authorization": "Bearer from-a-file"}).status_code
            == 404
        )
    monkeypatch.setenv("VISNERF_TOKEN", "from-the-env")
    from visnerf_server.settings import Settings

    env_settings = Settings(checkpoints_dir=ckpt_dir, state_dir=tmp_path / "state", client_dir=None)
    with TestClient(create_app(env_settings)) as client:
        assert (
            client.delete("/api/scenes/nope", headers={"Authorization": "Bearer from-the-env"}).status_code
            == 404
        )
        assert (
            client.delete("/api/scenes/nope", headers={"Authorization": "Bearer from-a-file"}).status_code
            == 403
        )
    assert not (tmp_path / "state" / "token").exists()


def test_stale_upload_temporaries_are_removed_at_start(ckpt_dir: Path, tmp_path: Path) -> None:
    old = ckpt_dir / ".upload-crashed.tmp"
    old.write_bytes(b"partial")
    os.utime(old, (1, 1))
    recent = ckpt_dir / ".upload-live.tmp"
    recent.write_bytes(b"in progress elsewhere")
    with TestClient(create_app(make_settings(ckpt_dir, tmp_path / "state"))):
        pass
    assert listing(ckpt_dir) == [".upload-live.tmp", "tiny.safetensors", "two.safetensors"]
