"""Orthographic scenes over REST: the scene says its projection, frames default to it, and a request
may ask for either projection; a lens of the other projection is refused."""

import io
import math
import time

import av
import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image
from server_helpers import make_settings

from visnerf.data.cameras import orbit_c2w
from visnerf.inference import choose_lens, load_scene
from visnerf.testing import make_tiny_checkpoint
from visnerf_server.app import create_app

CAMERA = {"azimuth": 30.0, "elevation": 20.0, "distance": 2.5, "view_height": 1.4}


@pytest.fixture
def ortho(tmp_path):
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    path = make_tiny_checkpoint(folder / "flat.safetensors", camera=CAMERA)
    with TestClient(create_app(make_settings(folder, tmp_path / "state"))) as client:
        yield client, load_scene(path)


def _png(response) -> np.ndarray:
    assert response.status_code == 200, response.text
    return np.asarray(Image.open(io.BytesIO(response.content)).convert("RGB"))


def test_scene_detail_names_the_projection(ortho) -> None:
    client, _ = ortho
    camera = client.get("/api/scenes/flat").json()["camera"]
    assert camera["projection"] == "orthographic" and camera["view_height"] == pytest.approx(1.4)
    assert camera["fov_deg"] == pytest.approx(math.degrees(2 * math.atan(0.7 / 2.5)))


def test_frames_default_to_the_scene_projection(ortho) -> None:
    client, scene = ortho
    c2w = orbit_c2w(30.0, 20.0, 2.5)
    expected = scene.render(c2w, None, 24, 24, {}, "full", view_height=1.4)
    got = _png(client.get("/api/scenes/flat/render", params={"width": 24, "height": 24}))
    assert np.array_equal(got, expected)
    perspective = scene.render(c2w, 30.0, 24, 24, {}, "full")
    asked = _png(client.post("/api/scenes/flat/render", json={"width": 24, "height": 24, "fov_deg": 30.0}))
    assert np.array_equal(asked, perspective) and not np.array_equal(asked, expected)
    wider = _png(client.get("/api/scenes/flat/render", params={"width": 24, "height": 24, "view_height": 2.8}))
    assert np.array_equal(wider, scene.render(c2w, None, 24, 24, {}, "full", view_height=2.8))


def test_a_perspective_scene_renders_orthographic_on_request(client) -> None:
    response = client.post("/api/scenes/tiny/render", json={"width": 16, "height": 16, "projection": "orthographic"})
    fov, view_height = choose_lens({"distance": 2.5, "fov_deg": 30.0}, projection="orthographic")
    assert fov is None and view_height == pytest.approx(2 * 2.5 * math.tan(math.radians(15.0)))
    assert response.status_code == 200
    assert client.get("/api/scenes/tiny").json()["camera"]["projection"] == "perspective"


@pytest.mark.parametrize("body", [
    {"projection": "orthographic", "fov_deg": 30.0},
    {"projection": "perspective", "view_height": 1.0},
    {"fov_deg": 30.0, "view_height": 1.0},
])
def test_a_lens_of_the_other_projection_is_refused(ortho, body) -> None:
    client, _ = ortho
    response = client.post("/api/scenes/flat/render", json={"width": 16, "height": 16, **body})
    assert response.status_code == 422 and "view_height" in response.json()["detail"], response.text


def test_bad_view_heights_are_refused_by_the_schema(ortho) -> None:
    client, _ = ortho
    for value in (0, -1, 1e7):
        assert client.post("/api/scenes/flat/render", json={"view_height": value}).status_code == 422


def _movie_frames(client: TestClient, body: dict) -> list[np.ndarray]:
    created = client.post("/api/scenes/flat/movies", json=body)
    assert created.status_code == 202, created.text
    job = created.json()
    deadline = time.monotonic() + 60.0
    while (status := client.get(job["status_url"]).json())["state"] not in {"done", "failed", "cancelled"}:
        assert time.monotonic() < deadline, status
        time.sleep(0.05)
    assert status["state"] == "done", status
    with av.open(io.BytesIO(client.get(job["file_url"]).content)) as container:
        return [f.to_ndarray(format="rgb24") for f in container.decode(container.streams.video[0])]


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * math.log10(255.0**2 / mse)


def test_movies_of_an_orthographic_scene_are_orthographic(ortho) -> None:
    client, scene = ortho
    c2w = orbit_c2w(30.0, 20.0, 2.5)
    ortho_frame = scene.render(c2w, None, 48, 48, {}, "full", view_height=1.4)
    perspective = scene.render(c2w, 30.0, 48, 48, {}, "full")
    orbit = _movie_frames(client, {"orbit": 2, "fps": 10, "width": 48, "height": 48})
    assert _psnr(orbit[0], ortho_frame) > max(35.0, _psnr(orbit[0], perspective) + 5.0)
    wide = {"azimuth": 30, "elevation": 20, "distance": 2.5, "view_height": 2.8}
    path = {"version": 1, "keyframes": [{"time": 0.0, "camera": wide}, {"time": 0.1, "camera": wide}]}
    framed = _movie_frames(client, {"path": path, "fps": 10, "width": 48, "height": 48})
    assert _psnr(framed[0], scene.render(c2w, None, 48, 48, {}, "full", view_height=2.8)) > 35.0
    mixed = {**path, "keyframes": [path["keyframes"][0], {"time": 0.1, "camera": {"fov": 30}}]}
    refused = client.post("/api/scenes/flat/movies", json={"path": mixed, "width": 48, "height": 48})
    assert refused.status_code == 422 and "keyframes[1].camera.fov" in refused.text
