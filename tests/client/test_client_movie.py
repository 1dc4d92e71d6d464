"""The movie panel: keyframes recorded from the view, the preview played in the viewer, the render
job (progress, cancel, download of a playable MP4), the path saved as JSON and loaded back, and the
path shared in the URL."""

import itertools
import json
import re
from urllib.parse import parse_qs, urlencode, urlparse

import numpy as np
import pytest
from client_helpers import camera_readout, canvas_pixels, wait_for_full_frame

pytestmark = [pytest.mark.browser, pytest.mark.slow]

PARAM = '.param[data-set="A"][data-param="{}"] input[type=number]'


def strip_times(page) -> list[float]:
    return [float(v) for v in page.locator("#kf-strip .kf-time").evaluate_all("els => els.map(e => e.value)")]


def path_in_page(page) -> dict:
    """The path the page holds, as the JSON document (no thumbnails)."""
    return page.evaluate(
        """() => {
            const p = window.__visnerfState.path;
            return {...p, keyframes: p.keyframes.map(({time, camera, params}) => ({time, camera, params}))};
        }"""
    )


def record_two_keyframes(page, server_url: str) -> tuple[tuple, tuple]:
    """Open vortex_tf1, add a keyframe, turn the view a quarter round and up, change a parameter,
    add a second keyframe. Returns the two camera readouts."""
    page.goto(server_url + "/?scene=vortex_tf1&res=128")
    seq = wait_for_full_frame(page)
    assert page.locator("#kf-strip .kf").count() == 0
    assert page.locator("#kf-empty").is_visible()
    assert page.locator("#movie-preview").is_disabled() and page.locator("#movie-render").is_disabled()
    first = camera_readout(page)
    page.click("#kf-add")
    page.focus("#viewport")
    for _ in range(6):
        page.keyboard.press("Shift+ArrowRight")  # 6 x 15 degrees
    page.keyboard.press("Shift+ArrowUp")
    page.fill(PARAM.format("opacity_high"), "0.3")
    page.press(PARAM.format("opacity_high"), "Enter")
    wait_for_full_frame(page, seq)
    second = camera_readout(page)
    page.click("#kf-add")
    assert page.locator("#kf-strip .kf").count() == 2
    assert strip_times(page) == [0.0, 2.0], "keyframes are spaced 2 s apart by default"
    return first, second


def test_keyframes_preview_and_render_a_playable_mp4(page, base_url):
    av = pytest.importorskip("av")
    first, second = record_two_keyframes(page, base_url)
    assert first[0] != second[0] and first[1] != second[1]
    # The cards show thumbnails of the view they recorded.
    thumbs = page.locator("#kf-strip .kf-thumb").evaluate_all("imgs => imgs.map(i => i.src)")
    assert all(src.startswith("data:image/jpeg") for src in thumbs)
    assert "2 keyframes" in page.inner_text("#movie-summary")
    path = path_in_page(page)
    assert path["keyframes"][0]["camera"]["azimuth"] == pytest.approx(first[0], abs=0.06)
    assert path["keyframes"][1]["camera"]["elevation"] == pytest.approx(second[1], abs=0.06)
    assert path["keyframes"][1]["params"]["opacity_high"] == pytest.approx(0.3)

    # Typing in the panel's inputs never moves the camera (the view's keyboard shortcuts stay off).
    before = camera_readout(page)
    time_input = page.locator("#kf-strip .kf-time").nth(1)
    time_input.click()
    for key in ["ArrowLeft", "ArrowRight", "r", "Home", "-", "+"]:
        page.keyboard.press(key)
    page.locator("#movie-fps").click()
    page.keyboard.press("ArrowLeft")
    page.keyboard.press("r")
    assert camera_readout(page) == before

    # Preview: the path plays in the view as preview frames, ending at the last keyframe.
    seq = wait_for_full_frame(page)
    page.click('#kf-strip .kf[data-index="0"] .kf-show')  # back to the first keyframe
    seq = wait_for_full_frame(page, seq)
    assert camera_readout(page)[:2] == pytest.approx(first[:2], abs=0.06)
    start = canvas_pixels(page)
    n_before = page.evaluate("window.__visnerfStats.frames.length")
    page.click("#movie-preview")
    assert page.get_attribute("#movie-panel", "data-playing") == "true"
    shots = []
    while page.get_attribute("#movie-panel", "data-playing") == "true" and len(shots) < 200:
        shots.append((page.get_attribute("#canvas-a", "data-seq"), canvas_pixels(page)))
        page.wait_for_timeout(60)
    page.wait_for_function("!document.querySelector('#movie-panel').dataset.playing", timeout=10_000)
    shown = page.evaluate(f"window.__visnerfStats.frames.slice({n_before}).map(f => f.quality)")
    assert shown.count("preview") >= 3, f"the preview showed too few frames: {shown}"
    assert len({s for s, _ in shots}) >= 2, "the view did not change during the preview"
    pictures = [start] + [pixels for _, pixels in shots]
    assert any(
        a.shape != b.shape or np.abs(a.astype(int) - b.astype(int)).mean() > 1.0
        for a, b in itertools.pairwise(pictures)
    ), "the frames shown during the preview are all alike"
    wait_for_full_frame(page, seq)
    assert camera_readout(page)[:2] == pytest.approx(second[:2], abs=0.06)

    # A time edited on its card; the estimate follows.
    time_input = page.locator("#kf-strip .kf-time").nth(1)
    time_input.fill("1")
    time_input.press("Tab")
    assert strip_times(page) == [0.0, 1.0]
    page.fill("#movie-fps", "4")
    page.fill("#movie-width", "64")
    page.fill("#movie-height", "64")
    page.select_option("#movie-format", "mp4")
    assert page.inner_text("#movie-estimate") == "5 frames"

    # Render: progress while it runs, then a download link to a playable MP4.
    page.click("#movie-render")
    assert page.locator("#movie-job").is_visible()
    page.wait_for_function("document.querySelector('#movie-job').dataset.state === 'done'", timeout=120_000)
    assert page.inner_text("#movie-status").startswith("Done: 5 / 5 frames")
    assert page.evaluate(
        "[document.querySelector('#movie-progress').value, document.querySelector('#movie-progress').max]"
    ) == [5, 5]
    assert page.locator("#movie-cancel").is_hidden()
    assert page.locator("#alert").is_hidden()
    with page.expect_download() as info:
        page.click("#movie-download")
    download = info.value
    assert download.suggested_filename.endswith(".mp4")
    with av.open(download.path()) as container:
        stream = container.streams.video[0]
        frames = [frame.to_ndarray(format="rgb24") for frame in container.decode(stream)]
    assert len(frames) == 5
    assert frames[0].shape == (64, 64, 3)
    assert frames[0].std() > 1.0, "the first frame of the movie is blank"
    assert np.abs(frames[0].astype(int) - frames[-1].astype(int)).mean() > 1.0, "the movie does not move"


def test_cancel_a_running_movie(extra_server, page):
    """A long job on a server of its own (its pixels come out of that server's rate-limit bucket)."""
    server = extra_server("movie-cancel")
    record_two_keyframes(page, server.base_url)
    page.fill("#movie-fps", "30")
    page.fill("#movie-width", "128")
    page.fill("#movie-height", "128")
    page.click("#movie-render")
    page.wait_for_function("['queued', 'running'].includes(document.querySelector('#movie-job').dataset.state)")
    assert page.locator("#movie-render").is_disabled()
    # Progress while it runs: frames done of the total, the speed and the time left.
    page.wait_for_function(
        r"/^Rendering: \d+ \/ 61 frames · [\d.]+ fps · \d+ s left$/.test(document.querySelector('#movie-status').textContent)"
    )
    done, total = page.evaluate(
        "[document.querySelector('#movie-progress').value, document.querySelector('#movie-progress').max]"
    )
    assert 0 < done < total == 61
    page.click("#movie-cancel")
    page.wait_for_function("document.querySelector('#movie-job').dataset.state === 'cancelled'", timeout=20_000)
    assert page.inner_text("#movie-status").startswith("Cancelled")
    assert page.locator("#movie-download").is_hidden()
    assert page.locator("#movie-render").is_enabled()


def test_refused_movie_shows_the_servers_detail(page, base_url):
    record_two_keyframes(page, base_url)
    page.fill("#movie-width", "100000")
    page.click("#movie-render")
    page.wait_for_function("/422/.test(document.querySelector('#alert').textContent)")
    text = page.inner_text("#alert")
    assert "Could not start the movie" in text and "width" in text
    assert page.get_attribute("#movie-job", "data-state") == "failed"
    assert "width" in page.inner_text("#movie-status")


def test_failed_movie_shows_the_reason(page, base_url):
    """A job that fails on the server: its error is shown in the panel and the alert line."""

    def failed_status(route):
        if route.request.method != "GET":
            route.continue_()
            return
        body = {
            "job_id": "x", "scene_id": "vortex_tf1", "state": "failed", "frames_done": 2, "frames_total": 5,
            "error": "the movie encoder stopped: disk full", "frames_per_second": 3.0, "seconds_left": None,
        }  # fmt: skip
        route.fulfill(status=200, content_type="application/json", body=json.dumps(body))

    record_two_keyframes(page, base_url)
    page.route(re.compile(r".*/api/movies/[^/]+$"), failed_status)
    page.fill("#movie-fps", "2")
    page.fill("#movie-width", "64")
    page.fill("#movie-height", "64")
    page.click("#movie-render")
    page.wait_for_function("document.querySelector('#movie-job').dataset.state === 'failed'")
    assert page.inner_text("#movie-status") == "Failed: the movie encoder stopped: disk full"
    assert "disk full" in page.inner_text("#alert")
    assert page.locator("#movie-download").is_hidden()
    assert page.locator("#movie-render").is_enabled()


def test_path_saved_as_json_loads_back_the_same(page, base_url, tmp_path):
    record_two_keyframes(page, base_url)
    page.select_option("#path-camera", "linear")
    saved_in_page = path_in_page(page)
    with page.expect_download() as info:
        page.click("#path-save")
    download = info.value
    assert download.suggested_filename == "vortex_tf1_path.json"
    doc = json.loads(open(download.path()).read())
    assert doc["version"] == 1
    assert doc["camera_interpolation"] == "linear" and doc["param_interpolation"] == "linear"
    assert [k["time"] for k in doc["keyframes"]] == [0, 2]
    assert set(doc["keyframes"][0]) == {"time", "camera", "params"}
    assert set(doc["keyframes"][0]["camera"]) == {"azimuth", "elevation", "distance", "fov"}
    assert doc == saved_in_page

    # Remove both keyframes, then load the file back: the same path, the same strip.
    page.click('#kf-strip .kf[data-index="1"] .kf-remove')
    page.click('#kf-strip .kf[data-index="0"] .kf-remove')
    assert page.locator("#kf-strip .kf").count() == 0
    page.set_input_files("#path-file", download.path())
    page.wait_for_function("document.querySelectorAll('#kf-strip .kf').length === 2")
    assert path_in_page(page) == doc
    assert page.input_value("#path-camera") == "linear"
    assert strip_times(page) == [0.0, 2.0]

    # Moving a keyframe keeps the time slots; it swaps the views.
    page.click('#kf-strip .kf[data-index="0"] .kf-later')
    moved = path_in_page(page)
    assert [k["time"] for k in moved["keyframes"]] == [0, 2]
    assert moved["keyframes"][0]["camera"] == doc["keyframes"][1]["camera"]

    # A file that is not a path is refused in words, naming the field; the strip stays.
    bad = tmp_path / "bad.json"
    broken = json.loads(json.dumps(doc))
    broken["keyframes"][1]["camera"]["elevation"] = 120
    bad.write_text(json.dumps(broken))
    page.set_input_files("#path-file", str(bad))
    page.wait_for_function("/elevation/.test(document.querySelector('#alert').textContent)")
    assert "keyframes[1].camera.elevation" in page.inner_text("#alert")
    assert page.locator("#kf-strip .kf").count() == 2


def test_shared_url_restores_the_keyframe_strip(page, base_url):
    record_two_keyframes(page, base_url)
    saved = path_in_page(page)
    page.wait_for_function("new URL(location.href).searchParams.getAll('kf').length === 2")
    query = parse_qs(urlparse(page.url).query)
    assert len(query["kf"]) == 2 and all(len(kf.split("_")) == 5 + 2 for kf in query["kf"])
    shared = page.url
    page.goto(base_url + "/?scene=tangle_iso&res=128")  # somewhere else first
    wait_for_full_frame(page)
    assert page.locator("#kf-strip .kf").count() == 0
    page.goto(shared)
    wait_for_full_frame(page)
    assert page.locator("#kf-strip .kf").count() == 2
    restored = path_in_page(page)
    for a, b in zip(restored["keyframes"], saved["keyframes"], strict=True):
        assert a["time"] == b["time"]
        for name in ("azimuth", "elevation", "fov"):
            assert a["camera"][name] == pytest.approx(b["camera"][name], abs=0.006)
        assert a["camera"]["distance"] == pytest.approx(b["camera"]["distance"], abs=6e-5)
        assert a["params"] == pytest.approx(b["params"], abs=1e-6)
    # Keyframes restored from a link have their thumbnails rendered by the server.
    page.wait_for_function(
        "[...document.querySelectorAll('#kf-strip .kf-thumb')].every(i => i.complete && i.naturalWidth > 0)"
    )
    assert page.locator("#alert").is_hidden()


def test_malformed_path_in_link_falls_back_with_a_warning(page, base_url):
    query = urlencode([("scene", "vortex_tf1"), ("res", "128"), ("kf", "0_30_15_2.2_30_0.5_0.1"), ("kf", "oops")])
    page.goto(base_url + "/?" + query)
    wait_for_full_frame(page)
    text = page.inner_text("#alert")
    assert "camera path in this link is malformed" in text and "keyframe 2" in text
    assert page.get_attribute("#alert", "data-level") == "warning"
    assert page.locator("#kf-strip .kf").count() == 0
    # The rest of the link still applies, and the bad path leaves the address bar.
    page.wait_for_function("!new URL(location.href).searchParams.has('kf')")
