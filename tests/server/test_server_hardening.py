"""A server a stranger cannot starve: stream origins, message sizes, session and message limits;
errors that are the client's (explicit 422, 499 for an abandoned upload) against the server's
(500); health that answers while every render thread and the thread pool are busy; a frame cache
bounded in real memory; API docs with nothing from a CDN."""

import concurrent.futures
import json
import logging
import threading
import time
import tracemalloc
from pathlib import Path

import anyio.to_thread
import numpy as np
import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError
from server_helpers import ORBIT, TOKEN, listing, make_settings, serve_process
from starlette.websockets import WebSocketDisconnect
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from visnerf.meta_checks import RESERVED_PARAM_NAMES
from visnerf_server.app import create_app
from visnerf_server.frame_cache import CachedFrame, FrameCache
from visnerf_server.origins import origin_allowed
from visnerf_server.registry import Scene, SceneRegistry
from visnerf_server.routers.render import RESERVED_QUERY
from visnerf_server.settings import Settings

STREAM = "/api/scenes/tiny/stream"


def message(seq: int) -> str:
    return json.dumps(
        {"seq": seq, "camera": ORBIT, "width": 8, "height": 8, "params": {"a": 0.5}, "quality": "preview"}
    )


def next_frame_header(ws) -> dict:
    """Read past error messages to the next frame; returns its header (the image is read too)."""
    while True:
        header = ws.receive_json()
        if header["type"] == "frame":
            ws.receive_bytes()
            return header


def metric(client: TestClient, line_start: str) -> float:
    for line in client.get("/metrics").text.splitlines():
        if line.startswith(line_start + " "):
            return float(line.split()[-1])
    raise AssertionError(f"no metric {line_start}")


# --- origins ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("origin", "host", "allowed", "expected"),
    [
        (None, "127.0.0.1:8000", (), True),  # not a browser
        ("http://127.0.0.1:8000", "127.0.0.1:8000", (), True),
        ("HTTP://LocalHost:8000/", "localhost:8000", (), True),
        ("http://example.org", "example.org:80", (), True),  # default port on either side
        ("https://example.org:443", "example.org", (), True),
        ("http://[::1]:8000", "[::1]:8000", (), True),
        ("http://evil.example", "127.0.0.1:8000", (), False),
        ("http://127.0.0.1:9000", "127.0.0.1:8000", (), False),  # another port is another origin
        ("http://127.0.0.1:8000", None, (), False),
        ("null", "127.0.0.1:8000", (), False),
        ("not a url", "127.0.0.1:8000", (), False),
        ("https://viewer.example", "127.0.0.1:8000", ("https://viewer.example",), True),
        ("https://viewer.example:8443", "127.0.0.1:8000", ("https://viewer.example",), False),
    ],
)
def test_origin_rules(origin: str | None, host: str | None, allowed: tuple[str, ...], expected: bool) -> None:
    assert origin_allowed(origin, host, allowed) is expected


def test_allowed_origins_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("VISNERF_ALLOWED_ORIGINS", "https://A.example/, http://b.example:8080 ,")
    assert Settings().allowed_origins == ("https://a.example", "http://b.example:8080")
    monkeypatch.setenv("VISNERF_ALLOWED_ORIGINS", "ftp://files.example")
    with pytest.raises(ValidationError, match="must be http"):
        Settings()


def test_foreign_origin_is_refused_own_and_missing_accepted(ckpt_dir: Path, tmp_path: Path) -> None:
    settings = make_settings(ckpt_dir, tmp_path / "state", allowed_origins="https://viewer.example")
    with TestClient(create_app(settings)) as client:
        for origin in ("http://evil.example", "https://viewer.example.evil.example", "null"):
            with pytest.raises(WebSocketDisconnect) as refused:
                with client.websocket_connect(STREAM, headers={"origin": origin}):
                    pass
            assert refused.value.code == 1008
        for headers in ({}, {"origin": "http://testserver"}, {"origin": "https://viewer.example"}):
            with client.websocket_connect(STREAM, headers=headers) as ws:
                ws.send_text(message(1))
                assert next_frame_header(ws)["seq"] == 1
        assert metric(client, 'visnerf_stream_refused_total{reason="origin"}') == 3.0


# --- sessions and messages -------------------------------------------------------------------------


def test_sessions_over_the_cap_are_told_to_come_back(ckpt_dir: Path, tmp_path: Path) -> None:
    with TestClient(create_app(make_settings(ckpt_dir, tmp_path / "state", ws_max_sessions=2))) as client:
        server = client.app.state.server
        with client.websocket_connect(STREAM) as staying:
            with client.websocket_connect(STREAM) as leaving:
                for seq, ws in enumerate((staying, leaving)):
                    ws.send_text(message(seq))
                    next_frame_header(ws)  # both sessions are running
                assert server.stream_sessions == 2
                with client.websocket_connect(STREAM) as third:
                    error = third.receive_json()
                    assert error["status"] == 503 and error["retry_after"] == 1
                    assert "maximum of 2 stream sessions" in error["detail"]
                    with pytest.raises(WebSocketDisconnect) as closed:
                        third.receive_text()
                    assert closed.value.code == 1013
            deadline = time.monotonic() + 5
            while server.stream_sessions != 1:
                assert time.monotonic() < deadline
                time.sleep(0.01)
            with client.websocket_connect(STREAM) as again:
                again.send_text(message(7))
                assert next_frame_header(again)["seq"] == 7
        assert metric(client, 'visnerf_stream_refused_total{reason="sessions"}') == 1.0
        assert metric(client, "visnerf_stream_sessions") == 0.0


def test_messages_over_the_rate_get_429_and_the_session_stays_open(ckpt_dir: Path, tmp_path: Path) -> None:
    settings = make_settings(ckpt_dir, tmp_path / "state", ws_messages_per_s=2.0, ws_message_burst=3)
    with TestClient(create_app(settings)) as client, client.websocket_connect(STREAM) as ws:
        for seq in range(1, 7):  # 3 from the full bucket, then far faster than 2 a second
            ws.send_text(message(seq))
        refused: dict[int, dict] = {}
        frames: list[int] = []
        while len(refused) < 3 or 3 not in frames:
            reply = ws.receive_json()
            if reply["type"] == "frame":
                ws.receive_bytes()
                frames.append(reply["seq"])
            else:
                assert reply["status"] == 429, reply
                refused[reply["seq"]] = reply
        assert sorted(refused) == [4, 5, 6]
        assert all(0 < r["retry_after"] <= 0.5 for r in refused.values())
        assert "over 2 messages a second" in refused[4]["detail"]
        assert set(frames) <= {1, 2, 3}
        time.sleep(max(r["retry_after"] for r in refused.values()))
        ws.send_text(message(7))
        assert next_frame_header(ws)["seq"] == 7
        assert metric(client, 'visnerf_stream_refused_total{reason="rate"}') == 3.0


@pytest.mark.slow
def test_limits_against_a_real_server(ckpt_dir: Path, tmp_path: Path) -> None:
    """``visnerf serve`` hands ``ws_max_message_bytes`` (64 KiB) to the protocol: a bigger message
    closes the connection (1009) before the app sees it; origins are checked at the handshake."""
    with serve_process(ckpt_dir, tmp_path) as live:
        url = live.url.replace("http://", "ws://") + STREAM
        with connect(url) as ws:
            ws.send("x" * (100 * 1024))  # far below uvicorn's own default of 16 MiB
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=10)
            assert closed.value.rcvd is not None and closed.value.rcvd.code == 1009
        with connect(url) as ws:
            ws.send("x" * (60 * 1024))  # under the limit: the app answers, the session stays open
            assert json.loads(ws.recv(timeout=10))["status"] == 422
            ws.send(message(1))
            assert json.loads(ws.recv(timeout=30))["seq"] == 1
        with pytest.raises(InvalidStatus) as refused:
            connect(url, origin="http://evil.example")  # type: ignore[arg-type]
        assert refused.value.response.status_code == 403
        with connect(url, origin=live.url) as ws:  # type: ignore[arg-type]
            ws.send(message(2))
            assert json.loads(ws.recv(timeout=30))["seq"] == 2
    access = [json.loads(line) for line in live.log().splitlines() if line.startswith('{"method"')]
    assert {"method": "WS", "path": STREAM, "status": 403} in [
        {k: e[k] for k in ("method", "path", "status")} for e in access
    ]


# --- errors ---------------------------------------------------------------------------------------


def test_a_value_error_from_a_bug_is_a_500(client: TestClient, monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(self: SceneRegistry) -> list:
        raise ValueError("a bug, not the client's input")

    monkeypatch.setattr(SceneRegistry, "list", broken)
    response = TestClient(client.app, raise_server_exceptions=False).get("/api/scenes")  # no second lifespan
    assert response.status_code == 500
    assert "a bug" not in response.text


def test_client_input_errors_are_still_422(shared) -> None:
    client, _ = shared
    outside = client.get("/api/scenes/tiny/render", params={**ORBIT, "width": 8, "height": 8, "a": 3})
    assert outside.status_code == 422 and "outside its range" in outside.json()["detail"]
    unknown = client.post("/api/scenes/tiny/render", json={"width": 8, "height": 8, "params": {"b": 1}})
    assert unknown.status_code == 422 and "unknown parameter" in unknown.json()["detail"]


def _asgi_put(app, path: str, receive) -> list[dict]:
    """Drive the app with one PUT whose body comes from ``receive``; returns what it sent."""
    sent: list[dict] = []

    async def send(message: dict) -> None:
        sent.append(message)

    scope = {
        "type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "PUT", "scheme": "http",
        "path": path, "raw_path": path.encode(), "query_string": b"", "root_path": "",
        "headers": [(b"host", b"testserver"), (b"authorization", f"Bearer {TOKEN}".encode())],
        "client": ("127.0.0.1", 5000), "server": ("testserver", 80),
    }  # fmt: skip
    with concurrent.futures.ThreadPoolExecutor(1) as pool:  # a thread of its own has no event loop yet
        pool.submit(anyio.run, app, scope, receive, send).result()
    return sent


def test_an_abandoned_upload_is_one_log_line_with_499(
    client: TestClient, ckpt_dir: Path, templates, caplog: pytest.LogCaptureFixture
) -> None:
    data = templates["tiny"].read_bytes()
    messages = iter([
        {"type": "http.request", "body": data[:1000], "more_body": True},
        {"type": "http.disconnect"},
    ])  # fmt: skip

    async def receive() -> dict:
        return next(messages)

    before = listing(ckpt_dir)
    caplog.set_level(logging.INFO)
    caplog.clear()
    sent = _asgi_put(client.app, "/api/scenes/abandoned", receive)
    assert sent[0]["status"] == 499
    assert listing(ckpt_dir) == before
    access = [r for r in caplog.records if r.name == "visnerf_server.access"]
    assert [json.loads(r.getMessage())["status"] for r in access] == [499]
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert not any(r.exc_info for r in caplog.records)


def test_ready_names_failed_files_without_their_folder(
    ckpt_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import visnerf_server.registry as registry_module

    (ckpt_dir / "locked.safetensors").write_bytes(b"whatever")
    real_digest = registry_module.file_digest

    def digest(path: Path) -> str:
        if path.name == "locked.safetensors":
            raise PermissionError(13, "Permission denied", str(path))
        return real_digest(path)

    monkeypatch.setattr(registry_module, "file_digest", digest)
    with TestClient(create_app(make_settings(ckpt_dir, tmp_path / "state"))) as client:
        response = client.get("/api/ready")
    assert response.json()["failed"] == {"locked": "PermissionError: [Errno 13] Permission denied: 'locked.safetensors'"}
    assert str(tmp_path) not in response.text


# --- documentation ------------------------------------------------------------------------------


def test_docs_are_off_by_default_and_never_from_a_cdn(ckpt_dir: Path, tmp_path: Path) -> None:
    with TestClient(create_app(make_settings(ckpt_dir, tmp_path / "state"))) as client:
        assert client.get("/docs").status_code == 404
        assert client.get("/redoc").status_code == 404
        assert client.get("/openapi.json").status_code == 200
    assets = tmp_path / "assets"
    assets.mkdir()
    for name in ("swagger-ui-bundle.js", "swagger-ui.css", "redoc.standalone.js"):
        (assets / name).write_text(f"/* {name} */")
    with TestClient(create_app(make_settings(ckpt_dir, tmp_path / "state", docs_assets_dir=assets))) as client:
        for page, asset in (("/docs", "swagger-ui-bundle.js"), ("/redoc", "redoc.standalone.js")):
            html = client.get(page)
            assert html.status_code == 200
            assert f'"/docs-assets/{asset}"' in html.text
            assert "http://" not in html.text and "https://" not in html.text  # nothing from elsewhere
        assert client.get("/docs-assets/swagger-ui-bundle.js").text == "/* swagger-ui-bundle.js */"


# --- health while busy ------------------------------------------------------------------------------


class GatedRenderer:
    """Wraps a real scene; every frame drawn waits for ``gate``, then is grey."""

    def __init__(self, inner, gate: threading.Event) -> None:
        self.inner = inner
        self.gate = gate

    def __getattr__(self, name: str):
        return getattr(self.inner, name)

    def draw(self, view, *args, **kwargs) -> np.ndarray:
        self.gate.wait(20)
        return np.full((view.height, view.width, 3), 128, np.uint8)


def test_health_answers_while_renders_and_the_thread_pool_are_busy(ckpt_dir: Path, tmp_path: Path) -> None:
    settings = make_settings(ckpt_dir, tmp_path / "state", render_workers=2, render_queue_size=64, render_timeout_s=20)
    app = create_app(settings)
    gate = threading.Event()

    def hold_a_thread() -> dict:  # a sync route: one thread of AnyIO's pool until the gate opens
        gate.wait(20)
        return {}

    app.add_api_route("/test/hold", hold_a_thread)
    with TestClient(app) as client, concurrent.futures.ThreadPoolExecutor(60) as pool:
        server = app.state.server
        real = server.registry.get("tiny")
        with server.registry.mutation_lock:
            server.registry.install(Scene("gated", GatedRenderer(real.renderer, gate), real.path, "g1"))  # type: ignore[arg-type]
        limiter = client.portal.call(anyio.to_thread.current_default_thread_limiter)
        try:
            renders = [
                pool.submit(client.get, "/api/scenes/gated/render", params={**ORBIT, "width": 8 + i, "height": 8})
                for i in range(10)
            ]
            holders = [pool.submit(client.get, "/test/hold") for _ in range(50)]
            deadline = time.monotonic() + 10
            while server.queue.running < 2 or limiter.borrowed_tokens < limiter.total_tokens:
                assert time.monotonic() < deadline, (server.queue.running, limiter.borrowed_tokens)
                time.sleep(0.01)
            for path in ("/api/health", "/api/ready"):
                assert client.get(path).status_code == 200, path
            # answered while every worker thread was held: they need none
            assert limiter.borrowed_tokens == limiter.total_tokens
        finally:
            gate.set()
        assert [f.result(20).status_code for f in renders] == [200] * 10
        assert [f.result(20).status_code for f in holders] == [200] * 50


# --- the frame cache ------------------------------------------------------------------------------


def server_like_key(i: int) -> tuple:
    """A key shaped like ``FrameJob.key``: scene id, version, 16 floats of c2w, fov, size, params."""
    c2w = tuple(float(x) for x in np.random.default_rng(i).normal(size=16))
    return ("tiny", f"{i:064x}", c2w, 30.0 + i * 1e-6, 64, 64, (("a", 0.25 + i * 1e-9),), "preview", "jpeg")


def test_frame_cache_memory_is_bounded() -> None:
    """Thousands of tiny frames: tracemalloc's count of what the cache holds stays within what it
    counts (frames, keys, overhead), which stays within its budget."""
    budget = 4_000_000
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        cache = FrameCache(budget, max_entries=100_000)
        for i in range(6000):  # keys and frames made while tracing: what the cache keeps is counted
            cache.put(server_like_key(i), CachedFrame(bytes([i % 256]), "image/jpeg", 64, 64, float(i)))
        held = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert 1000 < len(cache) < 6000  # the budget, not the entry cap, evicted
    assert cache.n_bytes <= budget
    assert held <= cache.n_bytes, (held, cache.n_bytes, len(cache))
    assert held >= 0.6 * cache.n_bytes  # and the count is not wildly pessimistic


def test_frame_cache_entry_cap_and_metrics(ckpt_dir: Path, tmp_path: Path) -> None:
    cache = FrameCache(10**9, max_entries=3)
    for i in range(5):
        cache.put(("s", i), CachedFrame(b"x", "image/png", 8, 8, 1.0))
    assert len(cache) == 3 and cache.get(("s", 1)) is None and cache.get(("s", 4)) is not None
    settings = make_settings(ckpt_dir, tmp_path / "state", frame_cache_entries=2)
    with TestClient(create_app(settings)) as client:
        for width in (8, 9, 10):
            client.get("/api/scenes/tiny/render", params={**ORBIT, "width": width, "height": 8})
        assert metric(client, "visnerf_frame_cache_entries") == 2.0
        assert metric(client, "visnerf_frame_cache_bytes") == client.app.state.server.cache.n_bytes > 0


def test_render_query_names_are_reserved_for_axes() -> None:
    """An axis named like a render query parameter could not be set through GET: checkpoints
    with one are refused (``visnerf.meta_checks``)."""
    assert RESERVED_QUERY <= RESERVED_PARAM_NAMES
