"""``GET /api/scenes/{id}/bake``: built in the background lane (503 meanwhile), then served with
an ETag and cache headers, gzip on the wire, 304 to If-None-Match, bad settings refused, kept per
setting within its budget."""

import gzip
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient
from server_helpers import make_settings

from visnerf.bake.bake_file import parse_bake
from visnerf_server.app import create_app


def fetch_bake(client: TestClient, url: str, limit_s: float = 30.0, **kwargs):
    """Ask until the bake is built (503 with Retry-After meanwhile)."""
    deadline = time.monotonic() + limit_s
    while True:
        response = client.get(url, **kwargs)
        if response.status_code != 503:
            return response
        assert response.headers["retry-after"] == "1"
        assert time.monotonic() < deadline, "the bake was never built"
        time.sleep(0.05)


def test_a_bake_is_built_then_served_and_revalidated(client: TestClient) -> None:
    first = client.get("/api/scenes/tiny/bake?a=0.25")
    assert first.status_code == 503 and "being built" in first.json()["detail"]
    response = fetch_bake(client, "/api/scenes/tiny/bake?a=0.25")
    assert response.status_code == 200
    assert response.headers["content-type"] == "application/octet-stream"
    assert response.headers["content-encoding"] == "gzip"  # the test client asks for it, as browsers do
    bake = parse_bake(response.content)  # the client decompressed it
    assert bake.header.params == {"a": 0.25}
    assert response.headers["cache-control"] == "no-cache"
    etag = response.headers["etag"]
    again = client.get("/api/scenes/tiny/bake?a=0.25", headers={"If-None-Match": etag})
    assert again.status_code == 304 and again.headers["etag"] == etag
    other = fetch_bake(client, "/api/scenes/tiny/bake?a=0.75")
    assert other.status_code == 200 and other.headers["etag"] != etag
    metrics = client.get("/metrics").text
    assert "visnerf_bakes_built_total 2.0" in metrics
    assert "visnerf_bake_hits_total" in metrics and "visnerf_bake_seconds_count 2.0" in metrics


def test_naming_the_version_makes_it_immutable_and_plain_clients_get_plain_bytes(client: TestClient) -> None:
    detail = client.get("/api/scenes/tiny").json()
    version, default = detail["version"], detail["params"][0]["default"]
    response = fetch_bake(client, f"/api/scenes/tiny/bake?v={version}", headers={"Accept-Encoding": "identity"})
    assert response.status_code == 200
    assert "immutable" in response.headers["cache-control"] and "max-age=31536000" in response.headers["cache-control"]
    assert "content-encoding" not in response.headers
    assert parse_bake(response.content).header.params == {"a": default}
    stale = fetch_bake(client, "/api/scenes/tiny/bake?v=0000000000000000")
    assert stale.headers["cache-control"] == "no-cache"


@pytest.mark.parametrize(("query", "status", "words"), [
    ("a=2", 422, "outside its range"),
    ("b=0.5", 422, "unknown parameter"),
    ("a=x", 422, "must be a number"),
    ("a=0.1&a=0.2", 422, "given 2 times"),
])
def test_bad_settings_are_refused_and_build_nothing(client: TestClient, query, status, words) -> None:
    response = client.get(f"/api/scenes/tiny/bake?{query}")
    assert response.status_code == status and words in response.text
    assert "visnerf_bakes_built_total 0.0" in client.get("/metrics").text


def test_an_unknown_scene_is_404(client: TestClient) -> None:
    assert client.get("/api/scenes/nope/bake").status_code == 404


def test_bakes_are_kept_within_their_budget(ckpt_dir, tmp_path) -> None:
    settings = make_settings(ckpt_dir, tmp_path / "state", bake_cache_bytes=1)
    with TestClient(create_app(settings)) as client:
        state = client.app.state.server
        assert client.get("/api/scenes/tiny/bake?a=0.5").status_code == 503
        deadline = time.monotonic() + 30
        while "visnerf_bakes_built_total 1.0" not in client.get("/metrics").text:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert len(state.bakes) == 0 and state.bakes.n_bytes == 0  # larger than the budget: not kept


def test_the_bake_matches_the_bytes_the_model_bakes(client: TestClient, ckpt_dir) -> None:
    from visnerf.bake.scene_bake import bake_scene
    from visnerf.inference import load_scene

    response = fetch_bake(client, "/api/scenes/two/bake?t=1.5&iso=0.2")
    served = parse_bake(response.content)
    local = bake_scene(load_scene(ckpt_dir / "two.safetensors"), {"t": 1.5, "iso": 0.2})
    assert np.array_equal(served.raw, local.raw) and np.array_equal(served.codes, local.codes)
    assert len(gzip.compress(response.content, 1)) < len(response.content)
