"""Frames at the size of the screen: on a 1280x860 page the view settles on a full-quality frame
at its own size (times devicePixelRatio), after one at the training images' size; a chosen pixel
size keeps frames at that size."""

from urllib.parse import urlencode

import numpy as np
import pytest
from client_helpers import canvas_pixels, decode_png, get_bytes, wait_for_full_frame

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def stages(page) -> list[tuple[str, int, int]]:
    return [tuple(f) for f in page.evaluate(
        "window.__visnerfStats.frames.filter(f => f.channel === 'A').map(f => [f.stage, f.width, f.height])")]


def fitted_size(page) -> tuple[int, int]:
    """The frame filling the canvas's box at the training aspect, as the client computes it."""
    return tuple(page.evaluate("""() => {
        const c = document.querySelector('#canvas-a'), dpr = window.devicePixelRatio || 1;
        const [w, h] = window.__visnerfState.scene.image_size;
        const s = Math.min(Math.floor(c.clientWidth * dpr) / w, Math.floor(c.clientHeight * dpr) / h);
        return [Math.floor(w * s), Math.floor(h * s)];
    }"""))


def test_the_view_settles_at_its_own_size(page, base_url):
    page.set_viewport_size({"width": 1280, "height": 860})
    page.goto(base_url + "/?scene=vortex_tf1&az=30&el=20")
    wait_for_full_frame(page)
    width, height = fitted_size(page)
    assert width > 256, "the view is larger than the default full frame"
    shown = stages(page)
    assert shown[-1] == ("screen", width, height), shown
    trained = tuple(page.evaluate("window.__visnerfState.scene.image_size"))
    assert ("full", *trained) in shown[:-1], "the frame at the training images' size comes first"
    assert page.input_value("#resolution") == "screen"
    camera = page.evaluate("window.__visnerfState.camera")
    query = {"azimuth": camera["azimuth"], "elevation": camera["elevation"], "distance": camera["distance"],
             "width": width, "height": height, "quality": "full", "format": "png",
             "fov_deg": page.evaluate("window.__visnerfState.fovDeg")}
    expected = decode_png(get_bytes(f"{base_url}/api/scenes/vortex_tf1/render?{urlencode(query)}"))
    assert np.abs(canvas_pixels(page).astype(int) - expected.astype(int)).max() <= 2
    # New input: previews, the full frame, then the view's size again, in that order.
    before = len(shown)
    page.locator("#viewport").focus()
    page.keyboard.press("ArrowLeft")
    wait_for_full_frame(page)
    after = [s[0] for s in stages(page)[before:]]
    assert after[-1] == "screen" and "full" in after and after.index("full") < len(after) - 1, after


def test_a_chosen_resolution_keeps_its_size(page, base_url):
    page.set_viewport_size({"width": 1280, "height": 860})
    page.goto(base_url + "/?scene=vortex_tf1&res=128")
    wait_for_full_frame(page)
    assert "screen" not in [s[0] for s in stages(page)]
    assert page.eval_on_selector("#canvas-a", "c => [c.width, c.height]") == [128, 128]
    page.select_option("#resolution", "screen")
    wait_for_full_frame(page)
    assert stages(page)[-1][0] == "screen"
    page.wait_for_function("() => new URL(location.href).searchParams.get('res') === 'screen'")
