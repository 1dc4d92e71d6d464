"""An orthographic scene in the browser: it opens in an orthographic view (the frame the server
renders with the scene's view height), zoom changes the view height, the projection can be
switched and back, the view height is kept in a shared link, and a movie keyframe records it."""

import math
from urllib.parse import parse_qs, urlencode, urlparse

import numpy as np
import pytest
from client_helpers import canvas_pixels, decode_png, get_bytes, get_json, wait_for_full_frame
from conftest import start_server

from visnerf.testing import make_tiny_checkpoint

pytestmark = [pytest.mark.browser, pytest.mark.slow]
KEY_ZOOM = 1.1
"""The zoom of one + key (client/js/interaction.js)."""
CAMERA = {"azimuth": 30.0, "elevation": 20.0, "distance": 2.5, "view_height": 1.4}


@pytest.fixture(scope="module")
def ortho_url(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ortho")
    make_tiny_checkpoint(folder / "flat.safetensors", camera=CAMERA)
    server = start_server(folder, "orthographic")
    yield server.base_url
    server.stop()


def server_frame(base_url: str, **lens: float | str) -> np.ndarray:
    query = {"azimuth": 30, "elevation": 20, "distance": 2.5, "width": 128, "height": 128, "quality": "full",
             "format": "png", **lens}
    return decode_png(get_bytes(f"{base_url}/api/scenes/flat/render?{urlencode(query)}"))


def difference(a: np.ndarray, b: np.ndarray) -> int:
    assert a.shape == b.shape
    return int(np.abs(a.astype(int) - b.astype(int)).max())


def test_an_orthographic_scene_opens_orthographic_and_switches(page, ortho_url):
    assert get_json(ortho_url + "/api/scenes/flat")["camera"]["projection"] == "orthographic"
    page.goto(ortho_url + "/?scene=flat&res=128")
    seq = wait_for_full_frame(page)
    assert page.input_value("#projection") == "orthographic"
    assert page.inner_text("#lens-label") == "View height" and float(page.inner_text("#lens-value")) == 1.4
    ortho = server_frame(ortho_url, projection="orthographic", view_height=1.4)
    perspective = server_frame(ortho_url, projection="perspective", fov_deg=30)
    assert difference(ortho, perspective) > 30  # the two projections do differ here
    assert difference(canvas_pixels(page), ortho) <= 2
    # Zoom: the view height shrinks, the camera stays where it is, the link keeps it.
    page.locator("#viewport").focus()
    page.keyboard.press("+")
    seq = wait_for_full_frame(page, seq)
    height = 1.4 / KEY_ZOOM
    assert float(page.inner_text("#lens-value")) == pytest.approx(height, abs=1e-3)
    assert float(page.inner_text("#dist-value")) == 2.5
    page.wait_for_function("() => new URL(location.href).searchParams.get('vh') !== null")
    query = parse_qs(urlparse(page.url).query)
    assert float(query["vh"][0]) == pytest.approx(height, abs=1e-3) and "proj" not in query
    assert difference(canvas_pixels(page), server_frame(ortho_url, view_height=height)) <= 2
    # Perspective and back: the framing is kept by the lens rule, the frames follow.
    page.select_option("#projection", "perspective")
    seq = wait_for_full_frame(page, seq)
    assert page.inner_text("#lens-label") == "Field of view"
    page.wait_for_function("() => new URL(location.href).searchParams.get('proj') === 'p'")
    fov = math.degrees(2 * math.atan(0.7 / 2.5))  # the scene's: framing it alike at its distance
    assert float(page.inner_text("#lens-value").rstrip("°")) == pytest.approx(fov, abs=0.05)
    distance = height / (2 * math.tan(math.radians(fov / 2)))  # 2.5 / 1.1: the zoomed framing kept
    assert float(page.inner_text("#dist-value")) == pytest.approx(distance, abs=1e-3)
    assert difference(canvas_pixels(page), server_frame(ortho_url, fov_deg=fov, distance=distance)) <= 2
    page.select_option("#projection", "orthographic")
    wait_for_full_frame(page, seq)
    assert float(page.inner_text("#lens-value")) == pytest.approx(height, abs=2e-3)


def test_a_keyframe_of_an_orthographic_view_records_its_view_height(page, ortho_url):
    page.goto(ortho_url + "/?scene=flat&res=128")
    wait_for_full_frame(page)
    page.click("#kf-add")
    page.wait_for_function("() => new URL(location.href).searchParams.get('kf') !== null")
    row = parse_qs(urlparse(page.url).query)["kf"][0].split("_")
    assert row[4] == "h1.4"
    page.select_option("#projection", "perspective")
    page.click("#kf-add")
    assert "a path keeps one projection" in page.inner_text("#alert")
    assert len(parse_qs(urlparse(page.url).query)["kf"]) == 1
