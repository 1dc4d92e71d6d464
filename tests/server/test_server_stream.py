"""The interactive WebSocket stream: frames, stale-request dropping, errors that keep the
connection open, unknown scenes."""

import json
import threading

import pytest
from fastapi.testclient import TestClient
from server_helpers import AUTH, ORBIT, SlowRenderer, UntilCancelledRenderer, image_size
from starlette.websockets import WebSocketDisconnect

from visnerf.data.cameras import orbit_c2w
from visnerf_server.dependencies import get_frame_renderer
from visnerf_server.frame_cache import FrameCache
from visnerf_server.frames import FrameRenderer
from visnerf_server.metrics import Metrics
from visnerf_server.registry import Scene
from visnerf_server.render_queue import RenderQueue, WouldOutwaitError


def message(seq: int, **overrides: object) -> str:
    body = {
        "seq": seq,
        "camera": ORBIT,
        "fov_deg": 30.0,
        "width": 16,
        "height": 12,
        "params": {"a": 0.5},
        "quality": "preview",
        "format": "jpeg",
    }
    body.update(overrides)
    return json.dumps(body)


def receive_frame(ws) -> tuple[dict, bytes]:
    header = ws.receive_json()
    assert header["type"] == "frame", header
    return header, ws.receive_bytes()


def test_frame_header_then_image(client: TestClient) -> None:
    with client.websocket_connect("/api/scenes/tiny/stream") as ws:
        ws.send_text(message(1))
        header, data = receive_frame(ws)
        assert set(header) == {"type", "seq", "render_ms", "width", "height", "format", "dropped"}
        assert header["seq"] == 1 and header["width"] == 16 and header["height"] == 12
        assert header["format"] == "jpeg" and header["dropped"] == 0
        assert header["render_ms"] >= 0
        assert image_size(data) == ("JPEG", 16, 12)
        c2w = orbit_c2w(10.0, 5.0, 2.5).tolist()
        ws.send_text(message(2, camera={"c2w": c2w}, format="png", quality="full"))
        header, data = receive_frame(ws)
        assert header["seq"] == 2 and header["format"] == "png"
        assert image_size(data) == ("PNG", 16, 12)
        ws.send_text(message(3, format="webp"))
        header, data = receive_frame(ws)
        assert image_size(data)[0] == "WEBP"


def test_stale_requests_are_dropped(client: TestClient) -> None:
    registry = client.app.state.server.registry
    real = registry.get("tiny")
    slow = SlowRenderer(real.renderer, 0.25)
    with registry.mutation_lock:
        registry.install(Scene("slow", slow, real.path, "slow-v1"))  # type: ignore[arg-type]
    with client.websocket_connect("/api/scenes/slow/stream") as ws:
        for seq in range(1, 9):
            ws.send_text(message(seq, params={"a": seq / 10}))
        seen = []
        while not seen or seen[-1]["seq"] != 8:
            header, _ = receive_frame(ws)
            seen.append(header)
    seqs = [h["seq"] for h in seen]
    assert seqs == sorted(seqs) and seqs[-1] == 8
    assert len(seqs) < 8  # the newest message wins; stale ones are never rendered
    assert seen[-1]["dropped"] == 8 - len(seqs)
    assert slow.calls == len(seqs)
    metrics = client.get("/metrics").text
    assert f"visnerf_stream_dropped_frames_total {float(8 - len(seqs))}" in metrics


@pytest.mark.parametrize(
    ("text", "seq", "detail"),
    [
        ("not json", None, "not valid JSON"),
        ("[1, 2]", None, "Input should be a valid dictionary"),
        (json.dumps({"camera": ORBIT}), None, "seq: Field required"),
        (message(5, params={"a": 3.0}), 5, "outside its range [0.0, 1.0]"),
        (message(6, params={"b": 0.1}), 6, "unknown parameter(s) ['b']"),
        (message(7, width=5000), 7, "exceeds this server's limit of 2048"),
        (message(8, height=4), 8, "greater than or equal to 8"),
        (message(9, fov_deg=180), 9, "less than 180"),
        (message(10, camera={**ORBIT, "distance": 0}), 10, "greater than 0"),
        (
            message(11, camera={"c2w": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}),
            11,
            "rotation",
        ),
        (message(12, format="gif"), 12, "'png', 'jpeg' or 'webp'"),
        (message(13).replace("0.5", "NaN"), 13, "finite"),
    ],
)
def test_invalid_message_gets_error_and_connection_stays_open(
    shared,
    text: str,
    seq: int | None,
    detail: str,
) -> None:
    client, _ = shared
    with client.websocket_connect("/api/scenes/tiny/stream") as ws:
        ws.send_text(text)
        error = ws.receive_json()
        assert error["type"] == "error"
        assert error["status"] == 422
        assert error["seq"] == seq
        assert detail in error["detail"]
        ws.send_text(message(99))
        header, _ = receive_frame(ws)
        assert header["seq"] == 99


def test_binary_message_is_an_error(client: TestClient) -> None:
    with client.websocket_connect("/api/scenes/tiny/stream") as ws:
        ws.send_bytes(b"\x00\x01")
        assert ws.receive_json() == {
            "type": "error",
            "seq": None,
            "status": 422,
            "detail": "messages must be text JSON",
        }
        ws.send_text(message(1))
        assert receive_frame(ws)[0]["seq"] == 1


def test_unknown_scene_closes_with_4404(client: TestClient) -> None:
    with client.websocket_connect("/api/scenes/nope/stream") as ws:
        error = ws.receive_json()
        assert error == {"type": "error", "seq": None, "status": 404, "detail": "unknown scene 'nope'"}
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_text()
        assert closed.value.code == 4404


def test_scene_deleted_during_a_session(client: TestClient) -> None:
    with client.websocket_connect("/api/scenes/two/stream") as ws:
        ws.send_text(message(1, params={"t": 1.0}))
        assert receive_frame(ws)[0]["seq"] == 1
        assert client.delete("/api/scenes/two", headers=AUTH).status_code == 204
        ws.send_text(message(2, params={"t": 1.0}))
        error = ws.receive_json()
        assert error == {"type": "error", "seq": 2, "status": 404, "detail": "unknown scene 'two'"}


def test_repeated_view_comes_from_the_cache(client: TestClient) -> None:
    with client.websocket_connect("/api/scenes/tiny/stream") as ws:
        ws.send_text(message(1))
        _, first = receive_frame(ws)
        ws.send_text(message(2))
        header, second = receive_frame(ws)
    assert first == second
    assert header["render_ms"] == 0.0
    assert "visnerf_frame_cache_hits_total 1.0" in client.get("/metrics").text


def test_a_large_frame_refused_for_its_wait_is_a_503_with_that_wait(client: TestClient, monkeypatch) -> None:
    """A frame the queue refuses because the large frames ahead would hold it past the limit is
    answered at once with the estimated wait (no retries until the deadline); the session stays open."""
    calls: list[int] = []

    async def refuse(self, job, client=None):
        calls.append(job.width)
        raise WouldOutwaitError(12.3456, 30.0)

    monkeypatch.setattr(FrameRenderer, "render_async", refuse)
    with client.websocket_connect("/api/scenes/tiny/stream") as ws:
        ws.send_text(message(1))
        error = ws.receive_json()
        assert error["status"] == 503 and error["seq"] == 1 and error["retry_after"] == 12.346
        assert "would wait about 12 s" in error["detail"]
        monkeypatch.undo()
        ws.send_text(message(2))
        assert receive_frame(ws)[0]["seq"] == 2
    assert len(calls) == 1


def test_overload_errors_keep_the_session_open(client: TestClient) -> None:
    """A render past the time limit is a 504 error; a queue that stays full is a 503 with retry_after."""
    registry = client.app.state.server.registry
    real = registry.get("tiny")
    with registry.mutation_lock:
        registry.install(Scene("slow", SlowRenderer(real.renderer, 0.4), real.path, "slow-v1"))  # type: ignore[arg-type]
    server = client.app.state.server
    quick = FrameRenderer(server.queue, FrameCache(0), server.metrics, timeout_s=0.1, jpeg_quality=80)
    client.app.dependency_overrides[get_frame_renderer] = lambda: quick
    try:
        with client.websocket_connect("/api/scenes/slow/stream") as ws:
            ws.send_text(message(1))
            error = ws.receive_json()
            assert error["status"] == 504 and error["seq"] == 1
        full = RenderQueue(workers=1, queue_size=0, metrics=Metrics())
        release = threading.Event()
        blocker = full.submit(lambda: release.wait(10))
        busy = FrameRenderer(full, FrameCache(0), Metrics(), timeout_s=0.2, jpeg_quality=80)
        client.app.dependency_overrides[get_frame_renderer] = lambda: busy
        with client.websocket_connect("/api/scenes/tiny/stream") as ws:
            ws.send_text(message(2))
            error = ws.receive_json()
            assert error == {
                "type": "error",
                "seq": 2,
                "status": 503,
                "detail": "render queue is full; try again",
                "retry_after": 1,
            }
            release.set()
            blocker.result(5)
            ws.send_text(message(3))
            assert receive_frame(ws)[0]["seq"] == 3
        full.shutdown()
    finally:
        client.app.dependency_overrides.clear()


def test_a_newer_request_stops_a_large_frame(client: TestClient) -> None:
    registry = client.app.state.server.registry
    real = registry.get("tiny")
    blocking = UntilCancelledRenderer(real.renderer, min_pixels=512 * 512)
    with registry.mutation_lock:
        registry.install(Scene("big", blocking, real.path, "big-v1"))  # type: ignore[arg-type]
    with client.websocket_connect("/api/scenes/big/stream") as ws:
        ws.send_text(message(1, width=600, height=600, quality="full", format="png"))
        assert blocking.began.wait(10.0)
        ws.send_text(message(2))
        header, _ = receive_frame(ws)
        assert header["seq"] == 2 and header["dropped"] == 1  # the large frame was given up
        assert blocking.stopped == 1
        blocking.began.clear()
        ws.send_text(message(3, width=600, height=600, quality="full", format="png"))
        assert blocking.began.wait(10.0)  # alone, a large frame is rendered (closing the stream stops it)
