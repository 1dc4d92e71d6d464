"""Failures are shown in words: server stopped, server busy (503, retried), scene gone, refused input."""

import json
import re

import pytest
from client_helpers import ARTIFACTS, wait_for_full_frame

pytestmark = [pytest.mark.browser, pytest.mark.slow]

STREAM = re.compile(r".*/api/scenes/[^/]+/stream$")


def test_stopped_server_shows_unreachable_then_recovers(page, extra_server):
    (ARTIFACTS / "server-stop.log").unlink(missing_ok=True)
    server = extra_server("stop")
    page.goto(server.base_url + "/?scene=vortex_tf1&res=128")
    wait_for_full_frame(page)
    assert page.locator("#alert").is_hidden()
    server.stop()
    alert = page.locator("#alert")
    alert.wait_for(state="visible", timeout=15_000)
    page.wait_for_function(
        "/unreachable/i.test(document.querySelector('#alert').textContent)", timeout=15_000
    )
    assert alert.get_attribute("role") == "alert"
    # Moving the view while the server is down still answers in words, never a blank canvas.
    page.focus("#viewport")
    page.keyboard.press("ArrowLeft")
    page.wait_for_timeout(400)
    assert "unreachable" in alert.inner_text().lower()
    assert page.locator("#canvas-a").get_attribute("data-quality") == "full"  # the last frame stays
    assert page.evaluate("document.body.dataset.offline") == "true"  # ... dimmed
    seq = int(page.get_attribute("#canvas-a", "data-seq"))
    # The server comes back on the same address: the stream reconnects by itself (backoff), the
    # alert goes, and the view catches up with the change made while the server was away.
    port = int(server.base_url.rsplit(":", 1)[1])
    extra_server("stop", port=port)
    alert.wait_for(state="hidden", timeout=20_000)
    wait_for_full_frame(page, seq)
    assert page.evaluate("document.body.dataset.offline") is None


@pytest.mark.parametrize(("status", "detail", "said"), [
    (503, "render queue is full", "busy"),
    (429, "rate limit: 4000000 pixels a second per client", "rate limited"),
])
def test_busy_server_is_retried_after_the_delay(page, base_url, status, detail, said):
    """The stream answers the first request with 503 (queue full) or 429 (this client over its
    pixel rate): the page says which and asks again by itself after the delay."""
    answered = {"busy": 0}

    def handler(ws):
        server = ws.connect_to_server()

        def from_page(message):
            data = json.loads(message)
            if answered["busy"] == 0:
                answered["busy"] += 1
                reply = {"type": "error", "seq": data["seq"], "status": status, "detail": detail, "retry_after": 0.5}
                ws.send(json.dumps(reply))
            else:
                server.send(message)

        ws.on_message(from_page)

    page.route_web_socket(STREAM, handler)
    page.goto(base_url + "/?scene=vortex_tf1&res=128")
    # one look at the alert: it clears once the retry half a second later is answered
    page.wait_for_function("said => { const t = document.querySelector('#alert').textContent.toLowerCase();"
                           " return t.includes(said) && t.includes('retry in 0.5 s'); }", arg=said)
    wait_for_full_frame(page)
    page.locator("#alert").wait_for(state="hidden")
    assert answered["busy"] == 1


def test_scene_removed_while_streaming(page, base_url):
    """Close code 4404 and the scene's own URL answering 404 (deleted): the page says which scene
    is gone, in words, and stops asking for it."""
    calls = {"scene": 0}

    def stream(ws):
        ws.send(json.dumps({"type": "error", "seq": None, "status": 404, "detail": "unknown scene 'vortex_tf1'"}))
        ws.close(code=4404, reason="unknown scene")

    def scene(route):
        calls["scene"] += 1
        if calls["scene"] == 1:  # the page's first look succeeds; afterwards the scene is deleted
            route.continue_()
        else:
            route.fulfill(status=404, json={"detail": "unknown scene 'vortex_tf1'"})

    page.route_web_socket(STREAM, stream)
    page.route("**/api/scenes/vortex_tf1", scene)
    page.goto(base_url + "/?scene=vortex_tf1&res=128")
    page.wait_for_function("/no longer available/i.test(document.querySelector('#alert').textContent)")
    assert "vortex_tf1" in page.inner_text("#alert")
    assert calls["scene"] == 2


def test_unknown_scene_in_link_falls_back_with_a_warning(page, base_url):
    page.goto(base_url + "/?scene=does-not-exist&az=10")
    wait_for_full_frame(page)
    text = page.inner_text("#alert")
    assert "does-not-exist" in text and "not on this server" in text


def test_refused_request_shows_the_servers_detail(page, base_url):
    """Saving at an impossible size: the 422 detail from the server is shown, in words."""
    page.goto(base_url + "/?scene=vortex_tf1&res=128")
    wait_for_full_frame(page)
    page.fill("#export-width", "100000")
    page.fill("#export-height", "100000")
    page.click("#save-png")
    page.wait_for_function("/422/.test(document.querySelector('#alert').textContent)")
    text = page.inner_text("#alert")
    assert "Could not save the image" in text
    assert len(text) > 40, "the server's reason must be included"


def test_save_png_downloads_the_current_view(page, base_url):
    page.goto(base_url + "/?scene=vortex_tf1&res=128")
    wait_for_full_frame(page)
    page.fill("#export-width", "96")
    page.fill("#export-height", "80")
    with page.expect_download() as info:
        page.click("#save-png")
    download = info.value
    assert download.suggested_filename.endswith("_96x80.png")
    data = open(download.path(), "rb").read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert int.from_bytes(data[16:20], "big") == 96 and int.from_bytes(data[20:24], "big") == 80
