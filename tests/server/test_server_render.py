"""Single-frame rendering over HTTP: formats, cameras, parameters, caching, limits and errors."""

import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from server_helpers import ORBIT, SlowRenderer, image_size, make_settings

from visnerf.data.cameras import orbit_c2w
from visnerf.inference import load_scene
from visnerf.testing import make_tiny_checkpoint
from visnerf_server.app import create_app
from visnerf_server.dependencies import get_frame_renderer, get_render_queue
from visnerf_server.frame_cache import FrameCache
from visnerf_server.frames import FrameRenderer
from visnerf_server.metrics import Metrics
from visnerf_server.registry import Scene
from visnerf_server.render_queue import RenderQueue
from visnerf_server.settings import Settings

SMALL = {"camera": ORBIT, "width": 16, "height": 12}


@pytest.mark.parametrize(("fmt", "pil_format"), [("png", "PNG"), ("jpeg", "JPEG"), ("webp", "WEBP")])
def test_post_render_formats(client: TestClient, fmt: str, pil_format: str) -> None:
    response = client.post("/api/scenes/tiny/render", json={**SMALL, "format": fmt})
    assert response.status_code == 200
    assert response.headers["content-type"] == f"image/{fmt}"
    assert image_size(response.content) == (pil_format, 16, 12)
    assert float(response.headers["x-render-time-ms"]) > 0
    assert "render;dur=" in response.headers["server-timing"]
    assert response.headers["x-cache"] == "miss"


def test_identical_requests_hit_the_cache(client: TestClient) -> None:
    first = client.post("/api/scenes/tiny/render", json=SMALL)
    second = client.post("/api/scenes/tiny/render", json=SMALL)
    assert (first.headers["x-cache"], second.headers["x-cache"]) == ("miss", "hit")
    assert first.content == second.content
    assert second.headers["server-timing"].startswith("cache")
    other = client.post("/api/scenes/tiny/render", json={**SMALL, "params": {"a": 0.25}})
    assert other.headers["x-cache"] == "miss"


def test_orbit_and_equivalent_matrix_give_the_same_frame(client: TestClient) -> None:
    c2w = orbit_c2w(ORBIT["azimuth"], ORBIT["elevation"], ORBIT["distance"]).tolist()
    orbit = client.post("/api/scenes/tiny/render", json=SMALL)
    matrix = client.post("/api/scenes/tiny/render", json={**SMALL, "camera": {"c2w": c2w}})
    assert matrix.status_code == 200
    assert matrix.headers["x-cache"] == "hit"  # same normalised request
    assert matrix.content == orbit.content


def test_defaults_fill_everything_missing(client: TestClient) -> None:
    response = client.post("/api/scenes/two/render", json={"quality": "preview"})
    assert response.status_code == 200
    assert image_size(response.content) == ("PNG", 64, 64)  # the trained image size
    explicit = client.post(
        "/api/scenes/two/render",
        json={
            "camera": ORBIT,
            "fov_deg": 30.0,
            "width": 64,
            "height": 64,
            "params": {"t": 1.0, "iso": 0.5},
            "quality": "preview",
        },
    )
    assert explicit.headers["x-cache"] == "hit"


def test_parameters_change_the_image(client: TestClient) -> None:
    low = client.post("/api/scenes/tiny/render", json={**SMALL, "params": {"a": 0.0}})
    high = client.post("/api/scenes/tiny/render", json={**SMALL, "params": {"a": 1.0}})
    assert low.status_code == high.status_code == 200
    assert low.content != high.content


def test_get_render_with_query_parameters(client: TestClient) -> None:
    response = client.get(
        "/api/scenes/two/render",
        params={
            "azimuth": 10,
            "elevation": -5,
            "distance": 3,
            "fov_deg": 35,
            "width": 16,
            "height": 16,
            "t": 1.5,
            "iso": 0.2,
            "format": "jpeg",
            "quality": "preview",
        },
    )
    assert response.status_code == 200
    assert image_size(response.content) == ("JPEG", 16, 16)
    assert response.headers["cache-control"] == "no-cache"
    etag = response.headers["etag"]
    again = client.get(str(response.url), headers={"If-None-Match": etag})
    assert again.status_code == 304
    assert again.content == b""


def test_get_render_equals_post_render(client: TestClient) -> None:
    post = client.post("/api/scenes/two/render", json={**SMALL, "params": {"t": 0.5}, "format": "png"})
    get = client.get("/api/scenes/two/render", params={**ORBIT, "width": 16, "height": 12, "t": 0.5})
    assert get.status_code == 200
    assert get.headers["x-cache"] == "hit"
    assert get.content == post.content


def test_get_render_with_c2w_and_partial_orbit(client: TestClient) -> None:
    c2w = orbit_c2w(0.0, 0.0, 2.5)
    matrix = client.get(
        "/api/scenes/tiny/render",
        params={"c2w": ",".join(map(str, c2w.reshape(-1))), "width": 8, "height": 8},
    )
    assert matrix.status_code == 200
    partial = client.get(
        "/api/scenes/tiny/render", params={"azimuth": 0, "elevation": 0, "width": 8, "height": 8}
    )
    assert partial.status_code == 200  # distance from the scene's default camera (2.5)
    assert partial.content == matrix.content


BAD_BODIES = [
    ({**SMALL, "params": {"a": 1.5}}, "outside its range [0.0, 1.0]"),
    ({**SMALL, "params": {"a": -0.1}}, "outside its range [0.0, 1.0]"),
    ({**SMALL, "params": {"zeta": 0.5}}, "unknown parameter(s) ['zeta']"),
    ({**SMALL, "width": 4096}, "width 4096 exceeds this server's limit of 2048"),
    ({**SMALL, "height": 9000}, "less than or equal to 8192"),
    ({**SMALL, "width": 7}, "greater than or equal to 8"),
    ({**SMALL, "height": 0}, "greater than or equal to 8"),
    ({**SMALL, "fov_deg": 0}, "greater than 0"),
    ({**SMALL, "fov_deg": 180}, "less than 180"),
    ({**SMALL, "fov_deg": -20}, "greater than 0"),
    ({**SMALL, "camera": {**ORBIT, "distance": 0}}, "greater than 0"),
    ({**SMALL, "camera": {**ORBIT, "distance": -1}}, "greater than 0"),
    ({**SMALL, "camera": {**ORBIT, "elevation": 91}}, "less than or equal to 90"),
    ({**SMALL, "camera": {"azimuth": 0, "elevation": 0}}, "Field required"),
    ({**SMALL, "camera": {**ORBIT, "roll": 3}}, "Extra inputs are not permitted"),
    ({**SMALL, "camera": {"c2w": np.eye(4)[:3].tolist()}}, "at least 4 items"),
    (
        {**SMALL, "camera": {"c2w": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]]}},
        "proper rotation",
    ),
    (
        {**SMALL, "camera": {"c2w": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]]}},
        "proper rotation",
    ),
    ({**SMALL, "camera": {"c2w": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]}}, "last row"),
    (
        {**SMALL, "camera": {"c2w": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]] + [[0, 0, 0, 1, 5]]}},
        "at most 4",
    ),
    ({**SMALL, "quality": "ultra"}, "'preview' or 'full'"),
    ({**SMALL, "format": "gif"}, "'png', 'jpeg' or 'webp'"),
    ({**SMALL, "width": "wide"}, "valid integer"),
    ({**SMALL, "params": {"a": "high"}}, "valid number"),
    ({**SMALL, "params": [0.5]}, "valid dictionary"),
    ({**SMALL, "exposure": 2}, "Extra inputs are not permitted"),
    ({**SMALL, "camera": "front"}, "camera"),
    ([1, 2, 3], "valid dictionary"),
]


@pytest.mark.parametrize(("body", "expected"), BAD_BODIES)
def test_bad_render_requests_are_422_naming_the_problem(
    client: TestClient, body: object, expected: str
) -> None:
    response = client.post("/api/scenes/tiny/render", json=body)
    assert response.status_code == 422, response.text
    assert expected in str(response.json()["detail"])


@pytest.mark.parametrize(
    "raw",
    [
        '{"fov_deg": NaN}',
        '{"fov_deg": Infinity}',
        '{"params": {"a": NaN}}',
        '{"camera": {"azimuth": -Infinity, "elevation": 0, "distance": 2}}',
        '{"camera": {"c2w": [[NaN,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}}',
    ],
)
def test_non_finite_numbers_are_422(shared, raw: str) -> None:
    client, _ = shared
    response = client.post(
        "/api/scenes/tiny/render", content=raw, headers={"content-type": "application/json"}
    )
    assert response.status_code == 422
    assert "finite" in str(response.json()["detail"])


@pytest.mark.parametrize(
    ("query", "expected"),
    [
        ({"a": "2"}, "outside its range [0.0, 1.0]"),
        ({"a": "nan"}, "finite"),
        ({"a": "inf"}, "finite"),
        ({"a": "lots"}, "must be a number"),
        ({"b": "0.5"}, "unknown parameter(s) ['b']"),
        ({"azimuth": "nan"}, "finite"),
        ({"distance": "0"}, "greater than 0"),
        ({"width": "3000"}, "exceeds this server's limit"),
        ({"width": "abc"}, "valid integer"),
        ({"fov_deg": "180"}, "less than 180"),
        ({"format": "bmp"}, "'png', 'jpeg' or 'webp'"),
        ({"c2w": "1,2,3"}, "16 comma-separated numbers"),
        ({"c2w": ",".join(["1"] * 16)}, "c2w"),
        ({"c2w": ",".join(["0"] * 16), "azimuth": "3"}, "either c2w or azimuth"),
    ],
)
def test_bad_get_queries_are_422(shared, query: dict[str, str], expected: str) -> None:
    client, _ = shared
    response = client.get("/api/scenes/tiny/render", params={"width": 8, "height": 8, **query})
    assert response.status_code == 422, response.text
    assert expected in str(response.json()["detail"])


def test_repeated_query_parameter_is_422(shared) -> None:
    client, _ = shared
    response = client.get("/api/scenes/tiny/render?a=0.1&a=0.2&width=8&height=8")
    assert response.status_code == 422
    assert "given 2 times" in str(response.json()["detail"])


def test_unknown_scene_is_404(shared) -> None:
    client, _ = shared
    for response in (
        client.post("/api/scenes/nope/render", json=SMALL),
        client.get("/api/scenes/nope/render"),
    ):
        assert response.status_code == 404
        assert response.json() == {"detail": "unknown scene 'nope'"}


def test_server_limit_on_image_size_is_a_setting(ckpt_dir, tmp_path) -> None:
    settings = make_settings(ckpt_dir, tmp_path / "state", max_image_size=32)
    with TestClient(create_app(settings)) as client:
        assert client.post("/api/scenes/tiny/render", json={**SMALL, "width": 32}).status_code == 200
        response = client.post("/api/scenes/tiny/render", json={**SMALL, "width": 33})
        assert response.status_code == 422
        assert response.json()["detail"] == "width 33 exceeds this server's limit of 32 pixels"
        # default size is the trained size (64) clamped to the limit
        assert image_size(client.post("/api/scenes/tiny/render", json={}).content)[1:] == (32, 32)


def test_full_queue_is_503_with_retry_after(client: TestClient) -> None:
    """Override the render queue with one whose only slot is taken."""
    queue = RenderQueue(workers=1, queue_size=0, metrics=Metrics())
    release = threading.Event()
    blocker = queue.submit(lambda: release.wait(10))
    client.app.dependency_overrides[get_render_queue] = lambda: queue
    try:
        response = client.post("/api/scenes/tiny/render", json=SMALL)
        assert response.status_code == 503
        assert response.headers["retry-after"] == "1"
        assert "queue is full" in response.json()["detail"]
    finally:
        release.set()
        blocker.result(5)
        client.app.dependency_overrides.pop(get_render_queue)
        queue.shutdown()
    assert client.post("/api/scenes/tiny/render", json=SMALL).status_code == 200


def _install_slow(client: TestClient, delay_s: float) -> SlowRenderer:
    registry = client.app.state.server.registry
    real = registry.get("tiny")
    slow = SlowRenderer(real.renderer, delay_s)
    with registry.mutation_lock:
        registry.install(Scene("slow", slow, real.path, "slow-v1"))  # type: ignore[arg-type]
    return slow


def test_render_past_the_time_limit_is_504(client: TestClient) -> None:
    _install_slow(client, 0.4)
    server = client.app.state.server
    quick = FrameRenderer(server.queue, FrameCache(0), server.metrics, timeout_s=0.1, jpeg_quality=80)
    client.app.dependency_overrides[get_frame_renderer] = lambda: quick
    try:
        response = client.post("/api/scenes/slow/render", json=SMALL)
    finally:
        client.app.dependency_overrides.clear()
    assert response.status_code == 504
    assert "longer than the limit" in response.json()["detail"]


def test_waiting_past_the_time_limit_is_503(client: TestClient) -> None:
    slow = _install_slow(client, 0.5)
    queue = RenderQueue(workers=1, queue_size=4, metrics=Metrics())
    quick = FrameRenderer(queue, FrameCache(0), Metrics(), timeout_s=0.15, jpeg_quality=80)
    client.app.dependency_overrides[get_frame_renderer] = lambda: quick
    try:
        first = threading.Thread(
            target=client.post, args=("/api/scenes/slow/render",), kwargs={"json": SMALL}
        )
        first.start()
        while slow.calls == 0:
            time.sleep(0.01)
        response = client.post("/api/scenes/slow/render", json={**SMALL, "width": 8})
        first.join()
    finally:
        client.app.dependency_overrides.clear()
        queue.shutdown()
    assert response.status_code == 503
    assert response.headers["retry-after"] == "1"
    assert "waited in the queue" in response.json()["detail"]
    assert slow.calls == 1  # the cancelled request never rendered
    assert queue.waiting == 0 and queue.running == 0


def test_render_queue_accounting() -> None:
    metrics = Metrics()
    queue = RenderQueue(workers=1, queue_size=1, metrics=metrics)
    release = threading.Event()
    running = queue.submit(lambda: release.wait(5))
    waiting = queue.submit(lambda: 42)
    with pytest.raises(Exception, match="full"):
        queue.submit(lambda: 0)
    assert queue.waiting + queue.running == 2
    release.set()
    assert running.result(5) is True and waiting.result(5) == 42
    assert queue.run(lambda: 7, timeout=5) == 7
    queue.shutdown()
    assert queue.waiting == queue.running == 0
    assert metrics.rejected._value.get() == 1


def test_frame_cache_is_bounded_by_bytes() -> None:
    from visnerf_server.frame_cache import CachedFrame

    entry = FrameCache.entry_bytes(("s", 0), CachedFrame(b"x" * 40, "image/png", 8, 8, 1.0))
    assert entry > 40  # the key and the entry's overhead count too
    budget = 2 * entry + 10
    cache = FrameCache(max_bytes=budget)
    for i in range(5):
        cache.put(("s", i), CachedFrame(b"x" * 40, "image/png", 8, 8, 1.0))
    assert cache.n_bytes <= budget and len(cache) == 2
    assert cache.get(("s", 0)) is None and cache.get(("s", 4)) is not None
    cache.put(("s", "huge"), CachedFrame(b"x" * budget, "image/png", 8, 8, 1.0))
    assert cache.get(("s", "huge")) is None
    cache.drop_scene("s")
    assert len(cache) == 0 and cache.n_bytes == 0


def test_no_bad_input_produces_a_500(client: TestClient, settings: Settings) -> None:
    del settings
    junk = [None, True, -1, 0, 1e308, -1e308, 2**70, "x", "", [], {}, [[1]], {"c2w": None}]
    fields = ["camera", "fov_deg", "width", "height", "params", "quality", "format"]
    for field in fields:
        for value in junk:
            response = client.post("/api/scenes/tiny/render", json={**SMALL, field: value})
            assert response.status_code < 500, (field, value, response.text)
            if response.status_code != 200:
                assert "detail" in response.json()
    for raw in [b"", b"{", b"\xff\xfe", b"null", b'"text"', b"[]"]:
        response = client.post(
            "/api/scenes/tiny/render", content=raw, headers={"content-type": "application/json"}
        )
        assert 400 <= response.status_code < 500, raw


def test_range_ends_read_back_from_float32_are_accepted_and_clamped() -> None:
    """0.12 stored as float32 reads 0.1199999973: the end of the range, not outside it."""
    with tempfile.TemporaryDirectory() as tmp:
        scene = load_scene(make_tiny_checkpoint(Path(tmp) / "s.safetensors", [("p", [0.12, 0.1375, 0.155])]))
    low, high = float(np.float32(0.12)), float(np.float32(0.155))
    assert low < 0.12 and high > 0.155
    assert scene.resolve_params({"p": low}) == [0.12]
    assert scene.resolve_params({"p": high}) == [0.155]
    with pytest.raises(ValueError, match="outside its range"):
        scene.resolve_params({"p": 0.1199})


def test_large_frames_give_their_memory_back_after_encoding(client: TestClient, monkeypatch) -> None:
    """The trim comes after the frame is encoded (the scene's own trim ran before the 8-bit copy
    and the encoder's buffers), for large frames only, and also when the frame fails."""
    from visnerf import inference
    from visnerf_server import frames

    events: list[str] = []
    encode = frames.encode_image

    def encoded(*args, **kwargs):
        events.append("encode")
        return encode(*args, **kwargs)

    monkeypatch.setattr(frames, "encode_image", encoded)
    monkeypatch.setattr(frames, "release_free_memory", lambda: events.append("trim") or True)
    monkeypatch.setattr(inference, "release_free_memory", lambda: True)  # the scene's own trim
    monkeypatch.setattr(inference, "TRIM_AFTER_PIXELS", 16 * 12)
    assert client.post("/api/scenes/tiny/render", json={**SMALL, "width": 15}).status_code == 200
    assert events == ["encode"]
    events.clear()
    assert client.post("/api/scenes/tiny/render", json=SMALL).status_code == 200
    assert events == ["encode", "trim"]
    events.clear()
    monkeypatch.setattr(frames, "encode_image", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("encoder broke")))
    with pytest.raises(RuntimeError, match="encoder broke"):
        client.post("/api/scenes/tiny/render", json={**SMALL, "height": 13})
    assert events == ["trim"]
