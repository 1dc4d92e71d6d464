"""The view: first frame, orbit by drag and keys, zoom, reset, URL state, scene picker."""

import re
from urllib.parse import parse_qs, urlencode, urlparse

import numpy as np
import pytest
from client_helpers import (
    assert_changed,
    camera_readout,
    canvas_pixels,
    decode_png,
    get_bytes,
    get_json,
    wait_for_full_frame,
)

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def test_page_loads_and_shows_a_frame(page, base_url):
    page.goto(base_url + "/")
    wait_for_full_frame(page)
    pixels = canvas_pixels(page)
    assert pixels.shape[0] >= 16 and pixels.shape[1] >= 16
    assert pixels.std() > 1.0, "the canvas is blank"
    assert re.fullmatch(r"\d+ ms render", page.inner_text("#stat-render"))
    assert re.fullmatch(r"\d+×\d+", page.inner_text("#stat-size"))
    assert page.inner_text("#stat-quality").lower() == "full"
    assert page.inner_text("#badge-a").lower() == "full"
    assert page.locator("#alert").is_hidden()
    stats = page.evaluate(
        "({first: window.__visnerfStats.firstFrameMs, n: window.__visnerfStats.frames.length})"
    )
    assert stats["first"] is not None and stats["n"] >= 1
    # The scene picker lists the server's scenes.
    scenes = get_json(base_url + "/api/scenes")
    options = page.locator("#scene-select option:not([disabled])")
    assert sorted(options.evaluate_all("os => os.map(o => o.value)")) == sorted(s["id"] for s in scenes)


def test_drag_orbits_the_camera_and_changes_the_picture(page, base_url):
    page.goto(base_url + "/?scene=vortex_tf1&res=128")
    seq = wait_for_full_frame(page)
    before = canvas_pixels(page)
    az0, el0, dist0 = camera_readout(page)
    box = page.locator("#viewport").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    for i in range(1, 21):
        page.mouse.move(x + 6 * i, y + 3 * i)
        page.wait_for_timeout(20)
    page.mouse.up()
    wait_for_full_frame(page, seq)
    az1, el1, dist1 = camera_readout(page)
    assert az1 != pytest.approx(az0, abs=1.0), "dragging right must change the azimuth"
    assert el1 != pytest.approx(el0, abs=1.0), "dragging down must change the elevation"
    assert dist1 == dist0
    after = canvas_pixels(page)
    assert before.shape == after.shape
    assert_changed(before, after)
    qualities = page.evaluate("window.__visnerfStats.frames.map(f => f.quality)")
    assert "preview" in qualities, "no preview frame was shown while dragging"
    assert qualities[-1] == "full"
    # The URL follows the view.
    page.wait_for_function("(az) => new URL(location.href).searchParams.get('az') == String(az)", arg=az1)


def test_keyboard_orbits_zooms_and_resets(page, base_url):
    page.goto(base_url + "/?scene=vortex_tf1&res=128")
    wait_for_full_frame(page)
    az0, el0, dist0 = camera_readout(page)
    page.focus("#viewport")
    page.keyboard.press("ArrowRight")
    page.keyboard.press("ArrowUp")
    page.keyboard.press("+")
    page.wait_for_function("(az) => Number(document.querySelector('#az-value').textContent) !== az", arg=az0)
    az1, el1, dist1 = camera_readout(page)
    assert az1 == pytest.approx(az0 + 5, abs=0.11)
    assert el1 == pytest.approx(el0 + 5, abs=0.11)
    assert dist1 < dist0
    # Elevation stops at the pole, azimuth wraps.
    for _ in range(30):
        page.keyboard.press("Shift+ArrowUp")
    assert camera_readout(page)[1] == pytest.approx(89.9)
    page.keyboard.press("Home")
    assert camera_readout(page) == (az0, el0, dist0)
    page.dblclick("#viewport")
    assert camera_readout(page) == (az0, el0, dist0)


def test_wheel_zoom_is_clamped(page, base_url):
    page.goto(base_url + "/?scene=vortex_tf1&res=128")
    wait_for_full_frame(page)
    default = get_json(base_url + "/api/scenes/vortex_tf1")["camera"]["distance"]
    page.hover("#viewport")
    for _ in range(4):
        page.mouse.wheel(0, 1000)
    page.wait_for_timeout(50)
    assert camera_readout(page)[2] == pytest.approx(4.0 * default, rel=1e-3)
    for _ in range(6):
        page.mouse.wheel(0, -1000)
    page.wait_for_timeout(50)
    assert camera_readout(page)[2] == pytest.approx(0.3 * default, rel=1e-3)


def test_url_state_restores_the_view(page, base_url):
    state = {
        "scene": "vortex_tf1",
        "az": "-120",
        "el": "45",
        "dist": "3",
        "opacity_high": "0.25",
        "opacity_low": "0.07",
        "res": "128",
    }
    page.goto(base_url + "/?" + urlencode(state))
    wait_for_full_frame(page)
    assert camera_readout(page) == (-120.0, 45.0, 3.0)
    assert page.input_value('.param[data-set="A"][data-param="opacity_high"] input[type=number]') == "0.25"
    assert page.input_value('.param[data-set="A"][data-param="opacity_low"] input[type=number]') == "0.07"
    assert page.input_value("#scene-select") == "vortex_tf1"
    # The frame on screen is what the server renders for that state.
    scene = get_json(base_url + "/api/scenes/vortex_tf1")
    query = {
        "azimuth": -120, "elevation": 45, "distance": 3, "fov_deg": scene["camera"]["fov_deg"],
        "width": 128, "height": 128, "quality": "full", "format": "png", "opacity_high": 0.25, "opacity_low": 0.07,
    }  # fmt: skip
    expected = decode_png(get_bytes(f"{base_url}/api/scenes/vortex_tf1/render?{urlencode(query)}"))
    shown = canvas_pixels(page)
    assert shown.shape == expected.shape
    assert np.abs(shown.astype(int) - expected.astype(int)).max() <= 2
    # Out-of-range values in a shared link are clamped into the ranges, not sent to the server.
    page.goto(base_url + "/?scene=vortex_tf1&res=128&az=270&el=120&opacity_high=7&opacity_low=-1")
    wait_for_full_frame(page)
    az, el, _ = camera_readout(page)
    assert (az, el) == (-90.0, 89.9)
    assert page.input_value('.param[data-set="A"][data-param="opacity_high"] input[type=number]') == "0.8"
    assert page.input_value('.param[data-set="A"][data-param="opacity_low"] input[type=number]') == "0.02"
    page.wait_for_function("new URL(location.href).searchParams.get('opacity_high') === '0.8'")
    assert parse_qs(urlparse(page.url).query)["el"] == ["89.9"]


def test_scene_picker_shows_only_that_scenes_controls(page, base_url):
    page.goto(base_url + "/?scene=vortex_tf1&res=128")
    wait_for_full_frame(page)
    assert page.locator('.param[data-set="A"]').count() == 2
    page.select_option("#scene-select", "tangle_iso")
    page.wait_for_function("new URL(location.href).searchParams.get('scene') === 'tangle_iso'")
    wait_for_full_frame(page)
    names = page.locator('.param[data-set="A"]').evaluate_all("rows => rows.map(r => r.dataset.param)")
    assert names == ["isovalue"]
    assert "IR" in page.inner_text("#scene-kind")
    assert page.locator("#alert").is_hidden()
