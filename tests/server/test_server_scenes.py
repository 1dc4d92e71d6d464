"""Health, readiness, scene listing and details, metrics, access logs, the static client mount."""

import json
import logging
import math
import threading
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from server_helpers import ORBIT, make_settings
from starlette.websockets import WebSocketDisconnect

from visnerf_server.app import create_app
from visnerf_server.registry import SceneRegistry
from visnerf_server.settings import Settings


def test_health_reports_version_and_scene_count(client: TestClient) -> None:
    response = client.get("/api/health")
    assert response.status_code == 200
    body = response.json()
    assert body["status"] == "ok"
    assert body["version"] == "0.1.0"
    assert body["scenes"] == 2
    assert body["ready"] is True


def test_ready_after_load(client: TestClient) -> None:
    response = client.get("/api/ready")
    assert response.status_code == 200
    assert response.json() == {"ready": True, "scenes": 2, "failed": {}}


def test_ready_is_503_until_scenes_are_loaded(settings: Settings, monkeypatch: pytest.MonkeyPatch) -> None:
    release = threading.Event()
    original = SceneRegistry.load_all

    def gated_load_all(self: SceneRegistry, *args: object, **kwargs: object) -> dict[str, str]:
        assert release.wait(10)
        return original(self, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(SceneRegistry, "load_all", gated_load_all)
    app = create_app(settings.model_copy(update={"background_load": True}))
    with TestClient(app) as client:
        response = client.get("/api/ready")
        assert response.status_code == 503
        assert response.headers["retry-after"] == "1"
        assert response.json()["ready"] is False
        health = client.get("/api/health")
        assert health.status_code == 200  # alive while loading
        assert health.json()["ready"] is False
        # The list too: a partial one would look final.
        listing = client.get("/api/scenes")
        assert listing.status_code == 503 and listing.headers["retry-after"] == "1"
        assert "still loading" in listing.json()["detail"]
        # A scene whose file is there but not loaded yet: 503 with Retry-After, not 404.
        loading = client.get("/api/scenes/tiny")
        assert loading.status_code == 503 and loading.headers["retry-after"] == "1"
        assert "still loading" in loading.json()["detail"]
        assert client.get("/api/scenes/tiny/render?width=8&height=8").status_code == 503
        assert client.get("/api/scenes/no_such_scene").status_code == 404
        with client.websocket_connect("/api/scenes/tiny/stream") as ws:
            error = ws.receive_json()
            assert error["status"] == 503 and error["retry_after"] == 1
            with pytest.raises(WebSocketDisconnect) as closed:
                ws.receive_text()
            assert closed.value.code == 1013
        release.set()
        for _ in range(200):
            if client.get("/api/ready").status_code == 200:
                break
            time.sleep(0.02)
        assert client.get("/api/ready").json() == {"ready": True, "scenes": 2, "failed": {}}
        assert len(client.get("/api/scenes").json()) == 2


def test_list_scenes(client: TestClient) -> None:
    response = client.get("/api/scenes")
    assert response.status_code == 200
    scenes = response.json()
    assert [s["id"] for s in scenes] == ["tiny", "two"]
    tiny, two = scenes
    assert tiny["title"] == "Tiny" and tiny["kind"] == "dvr"
    assert two["kind"] == "ir"
    assert [p["name"] for p in two["params"]] == ["t", "iso"]
    assert two["params"][0] == {
        "name": "t",
        "min": 0.0,
        "max": 2.0,
        "values": [0.0, 1.0, 2.0],
        "default": 1.0,
    }


def test_scene_detail(client: TestClient) -> None:
    response = client.get("/api/scenes/two")
    assert response.status_code == 200
    scene = response.json()
    assert scene["id"] == "two"
    view_height = 2 * 2.5 * math.tan(math.radians(15.0))  # frames the orbit centre as the 30 degree view
    assert scene["camera"] == pytest.approx({"azimuth": 30.0, "elevation": 20.0, "distance": 2.5, "fov_deg": 30.0,
                                             "projection": "perspective", "view_height": view_height})
    assert scene["bbox"] == [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]]
    assert scene["image_size"] == [64, 64]  # [width, height]
    assert scene["background"] == [1.0, 1.0, 1.0]
    assert scene["training"]["dataset"] == "random"
    assert scene["training"]["val_psnr"] is None
    assert len(scene["version"]) == 16


@pytest.mark.parametrize(
    ("path", "status"),
    [
        ("/api/scenes/nope", 404),
        ("/api/scenes/Bad!", 422),
        ("/api/scenes/.hidden", 422),
        ("/api/scenes/%2e%2e", 422),
        ("/api/scenes/" + "a" * 65, 422),
    ],
)
def test_unknown_or_invalid_scene_id(shared, path: str, status: int) -> None:
    client, _ = shared
    response = client.get(path)
    assert response.status_code == status
    detail = response.json()["detail"]
    if status == 404:
        assert "unknown scene 'nope'" in detail
    else:
        assert detail[0]["loc"] == ["path", "scene_id"]


def test_bad_checkpoint_on_disk_is_skipped_not_fatal(ckpt_dir: Path, tmp_path: Path) -> None:
    (ckpt_dir / "broken.safetensors").write_bytes(b"not a checkpoint at all")
    (ckpt_dir / "Not-Valid-Id.safetensors").write_bytes(b"ignored")
    with TestClient(create_app(make_settings(ckpt_dir, tmp_path / "state"))) as client:
        ready = client.get("/api/ready")
        assert ready.status_code == 200
        assert list(ready.json()["failed"]) == ["broken"]
        assert "safetensors" in ready.json()["failed"]["broken"]
        assert [s["id"] for s in client.get("/api/scenes").json()] == ["tiny", "two"]


def test_missing_checkpoints_folder_serves_no_scenes(tmp_path: Path) -> None:
    with TestClient(create_app(make_settings(tmp_path / "absent", tmp_path / "state"))) as client:
        assert client.get("/api/ready").status_code == 200
        assert client.get("/api/scenes").json() == []


def test_metrics_exposition(client: TestClient) -> None:
    body = {"camera": ORBIT, "width": 16, "height": 16}
    assert client.post("/api/scenes/tiny/render", json=body).headers["x-cache"] == "miss"
    assert client.post("/api/scenes/tiny/render", json=body).headers["x-cache"] == "hit"
    assert client.get("/api/scenes/nope").status_code == 404
    response = client.get("/metrics")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/plain")
    text = response.text
    assert 'visnerf_render_seconds_count{quality="full"} 1.0' in text
    assert "visnerf_frame_cache_hits_total 1.0" in text
    assert "visnerf_render_queue_depth 0.0" in text
    assert "visnerf_renders_in_flight 0.0" in text
    assert "visnerf_stream_dropped_frames_total 0.0" in text
    assert 'visnerf_http_responses_total{status="200"} 2.0' in text
    assert 'visnerf_http_responses_total{status="404"} 1.0' in text


def test_many_apps_have_separate_metrics(settings: Settings) -> None:
    apps = [create_app(settings) for _ in range(3)]  # the global registry would refuse duplicates
    with TestClient(apps[0]) as first, TestClient(apps[1]) as second:
        first.get("/api/health")
        assert 'visnerf_http_responses_total{status="200"} 1.0' in first.get("/metrics").text
        assert 'status="200"' not in second.get("/metrics").text


def test_access_log_is_one_json_line_per_request(
    client: TestClient, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="visnerf_server.access")
    client.get("/api/health")
    client.get("/api/scenes/nope?x=secret")
    records = [r for r in caplog.records if r.name == "visnerf_server.access"]
    entries = [json.loads(r.getMessage()) for r in records]
    assert [(e["method"], e["path"], e["status"]) for e in entries] == [
        ("GET", "/api/health", 200),
        ("GET", "/api/scenes/nope", 404),
    ]
    assert all(isinstance(e["ms"], float) and e["ms"] >= 0 for e in entries)
    assert "secret" not in caplog.text  # query strings are not logged


def test_static_client_is_served_after_the_api(ckpt_dir: Path, tmp_path: Path) -> None:
    client_dir = tmp_path / "client"
    client_dir.mkdir()
    (client_dir / "index.html").write_text("<!doctype html><title>ViSNeRF</title>")
    with TestClient(create_app(make_settings(ckpt_dir, tmp_path / "state", client_dir=client_dir))) as client:
        page = client.get("/")
        assert page.status_code == 200
        assert "ViSNeRF" in page.text
        assert client.get("/api/health").json()["status"] == "ok"
        assert client.get("/api/scenes").status_code == 200


def test_openapi_documents_the_api(client: TestClient) -> None:
    paths = client.get("/openapi.json").json()["paths"]
    assert {"/api/health", "/api/scenes", "/api/scenes/{scene_id}", "/api/scenes/{scene_id}/render"} <= set(
        paths
    )
    assert {"get", "put", "delete"} <= set(paths["/api/scenes/{scene_id}"])
    assert {"get", "post"} <= set(paths["/api/scenes/{scene_id}/render"])


def test_oversize_request_body_is_refused(client: TestClient) -> None:
    response = client.post(
        "/api/scenes/tiny/render",
        content=b"{" + b" " * (2 * 1024 * 1024) + b"}",
        headers={"content-type": "application/json"},
    )
    assert response.status_code == 413
    assert "limit" in response.json()["detail"]
