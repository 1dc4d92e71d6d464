"""View A drawn in the browser from bakes (headless Chromium's software WebGL2): the local frame
against the server's full frame at the same camera and size, a drag that asks the server for
nothing, a settled slider that fetches one bake, and server frames where WebGL2 is missing."""

import math
from urllib.parse import urlencode

import numpy as np
import pytest
from client_helpers import canvas_pixels, decode_png, get_bytes

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.local_frames]
SMALL_PAGE = {"width": 760, "height": 560}
"""A view of a few hundred pixels: the software renderer takes about a second a frame there."""
LOCAL_TIMEOUT_MS = 90_000


def wait_local(page) -> dict:
    page.wait_for_function("window.__visnerfLocal && window.__visnerfLocal.source === 'local' "
                           "&& window.__visnerfSettled()", timeout=LOCAL_TIMEOUT_MS)
    return page.evaluate("({...window.__visnerfLocal})")


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(((a.astype(np.float64) - b.astype(np.float64)) ** 2).mean())
    return 10 * math.log10(255.0**2 / mse) if mse > 0 else float("inf")


def count_server_frames(page) -> dict:
    """Render requests the page makes, over HTTP and over the stream (installed before the page
    opens its stream; setting the counts to zero starts a new count)."""
    counts = {"http": 0, "stream": 0, "bakes": 0}

    def on_request(request) -> None:
        if "/render" in request.url:
            counts["http"] += 1

    def on_response(response) -> None:
        if "/bake" in response.url and response.status == 200:
            counts["bakes"] += 1

    page.on("request", on_request)
    page.on("response", on_response)
    page.on("websocket", lambda ws: ws.on("framesent", lambda _: counts.__setitem__("stream", counts["stream"] + 1)))
    return counts


def open_counted(page, base_url: str, scene: str) -> dict:
    """The scene drawn locally, and the server frames and bakes the page asks for from then on."""
    counts = count_server_frames(page)
    page.set_viewport_size(SMALL_PAGE)
    page.goto(base_url + f"/?scene={scene}")
    wait_local(page)
    counts.update(http=0, stream=0, bakes=0)
    return counts


@pytest.mark.parametrize("scene", ["vortex_tf1", "tangle_iso"])
def test_the_local_frame_matches_the_server_frame(page, base_url, scene):
    page.set_viewport_size(SMALL_PAGE)
    page.goto(base_url + f"/?scene={scene}&az=35&el=20")
    info = wait_local(page)
    assert page.inner_text("#badge-a").lower() == "local"
    assert info["bakesFetched"] == 1 and info["textureBytes"] > 0 and info["drawMs"] > 0
    camera = page.evaluate("window.__visnerfState.camera")
    query = {"azimuth": camera["azimuth"], "elevation": camera["elevation"], "distance": camera["distance"],
             "width": info["width"], "height": info["height"], "quality": "full", "format": "png",
             "fov_deg": page.evaluate("window.__visnerfState.fovDeg")}
    server = decode_png(get_bytes(f"{base_url}/api/scenes/{scene}/render?{urlencode(query)}"))
    local = canvas_pixels(page)
    assert local.shape == server.shape
    assert psnr(local, server) >= 30.0


def test_a_drag_asks_the_server_for_nothing(page, base_url):
    counts = open_counted(page, base_url, "vortex_tf1")
    before = page.evaluate("window.__visnerfState.camera.azimuth")
    box = page.locator("#canvas-a").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    for step in range(1, 6):
        page.mouse.move(x + 12 * step, y + 3 * step, steps=2)
    page.mouse.up()
    wait_local(page)
    assert page.evaluate("window.__visnerfState.camera.azimuth") != before
    assert counts == {"http": 0, "stream": 0, "bakes": 0}
    frames = page.evaluate("window.__visnerfStats.frames.filter(f => f.quality === 'local').length")
    assert frames >= 2


def test_a_settled_slider_fetches_one_bake(page, base_url):
    counts = open_counted(page, base_url, "tangle_iso")
    axis = page.evaluate("window.__visnerfState.scene.params[0]")
    for k in range(1, 6):  # a slider dragged through five values, then left
        value = axis["min"] + (axis["max"] - axis["min"]) * (0.3 + 0.05 * k)
        page.evaluate("([n, v]) => window.__visnerfState.setParam(n, v, {set: 'A', interactive: true})",
                      [axis["name"], value])
        page.wait_for_timeout(40)
    page.wait_for_function("window.__visnerfLocal.bakesFetched === 2 && window.__visnerfLocal.source === 'local'",
                           timeout=LOCAL_TIMEOUT_MS)
    wait_local(page)
    assert counts["bakes"] == 1, counts
    assert counts["stream"] + counts["http"] >= 1, "the moving slider was drawn by the server meanwhile"
    held = page.evaluate("window.__visnerfState.params")
    assert held[axis["name"]] == pytest.approx(value)


def test_without_webgl2_the_server_draws_and_says_why(page, base_url):
    page.add_init_script("""(() => {
        const original = HTMLCanvasElement.prototype.getContext;
        HTMLCanvasElement.prototype.getContext = function (kind, ...rest) {
            return kind === 'webgl2' ? null : original.call(this, kind, ...rest);
        };
    })()""")
    page.set_viewport_size(SMALL_PAGE)
    page.goto(base_url + "/?scene=vortex_tf1")
    page.wait_for_function("window.__visnerfSettled() && document.querySelector('#canvas-a').dataset.quality === 'full'",
                           timeout=LOCAL_TIMEOUT_MS)
    assert "WebGL2 is not available" in page.inner_text("#local-status")
    assert page.evaluate("window.__visnerfLocal.source") == "server"
    assert page.inner_text("#badge-a").lower() == "full"


def test_the_toggle_forces_server_frames(page, base_url):
    page.set_viewport_size(SMALL_PAGE)
    page.goto(base_url + "/?scene=vortex_tf1")
    wait_local(page)
    page.check("#server-frames")
    page.wait_for_function("window.__visnerfSettled() && document.querySelector('#canvas-a').dataset.quality === 'full'",
                           timeout=LOCAL_TIMEOUT_MS)
    assert page.evaluate("window.__visnerfLocal.source") == "server"
    assert page.evaluate("localStorage.getItem('visnerf.serverFrames')") == "1"
    page.uncheck("#server-frames")
    wait_local(page)
