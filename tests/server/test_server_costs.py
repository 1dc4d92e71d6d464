"""Costs per request and per client: pixel budgets per quality (422 naming the limit and the size
asked for), renders stopped when their deadline passes or their client leaves, the per-client rate
limit (429 with Retry-After), previews ahead of queued full frames, occupancy grid builds in the
render queue, and a real ``visnerf serve`` stopped by SIGTERM within 10 s with a large render in
flight."""

import asyncio
import contextlib
import gc
import json
import math
import signal
import threading
import time
import weakref
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient
from server_helpers import AUTH, ORBIT, image_size, make_settings, serve_process

from visnerf.inference import FrameView, RenderCancelled
from visnerf_server.app import create_app
from visnerf_server.frames import FrameJob
from visnerf_server.metrics import Metrics
from visnerf_server.render_queue import Lane, QueueFullError, RenderQueue, RenderTimeoutError, WouldOutwaitError

SMALL = {"camera": ORBIT, "width": 16, "height": 12}
BIG = 2048
"""A full frame of the tiny scene this wide and high takes seconds to render on a 2-core CPU."""
BIG_PIXELS = BIG * BIG
FULL_RENDERS_DONE = 'visnerf_render_seconds_count{{quality="full"}} {}.0'
"""The /metrics line counting full-quality renders that finished."""


# --- pixel budgets -------------------------------------------------------------------------------


def test_frames_over_the_pixel_budget_are_refused_naming_the_limit_and_the_size(shared) -> None:
    client, _ = shared
    full = client.post("/api/scenes/tiny/render", json={**SMALL, "width": 2000, "height": 1100})
    assert full.status_code == 422
    assert full.json()["detail"] == (
        "a full frame of 2000x1100 = 2200000 pixels exceeds this server's limit of 2073600 pixels "
        "for full frames (max_full_pixels)"
    )
    preview = client.get(
        "/api/scenes/tiny/render", params={**ORBIT, "width": 600, "height": 600, "quality": "preview"}
    )
    assert preview.status_code == 422
    assert "600x600 = 360000 pixels exceeds this server's limit of 262144 pixels for preview frames" in (
        preview.json()["detail"]
    )
    with client.websocket_connect("/api/scenes/tiny/stream") as ws:
        ws.send_text(json.dumps({"seq": 5, "camera": ORBIT, "width": 600, "height": 600, "quality": "preview"}))
        error = ws.receive_json()
        assert error["status"] == 422 and error["seq"] == 5
        assert "360000 pixels exceeds" in error["detail"] and "max_preview_pixels" in error["detail"]
        ws.send_text(json.dumps({"seq": 6, "camera": ORBIT, "width": 512, "height": 512, "quality": "preview"}))
        assert ws.receive_json()["seq"] == 6  # the budget itself is allowed
        assert image_size(ws.receive_bytes())[1:] == (512, 512)


def test_pixel_budgets_are_settings_and_a_default_size_fits_them(ckpt_dir: Path, tmp_path: Path) -> None:
    settings = make_settings(ckpt_dir, tmp_path / "state", max_preview_pixels=1024, max_full_pixels=2048)
    with TestClient(create_app(settings)) as client:
        url = "/api/scenes/tiny/render"
        assert client.post(url, json={**SMALL, "width": 32, "height": 32, "quality": "preview"}).status_code == 200
        refused = client.post(url, json={**SMALL, "width": 33, "height": 32, "quality": "preview"})
        assert refused.status_code == 422 and "limit of 1024 pixels for preview" in refused.json()["detail"]
        assert client.post(url, json={**SMALL, "width": 64, "height": 32}).status_code == 200
        # No size given: the trained 64x64, scaled down (aspect kept) to fit the quality's budget.
        preview = client.post(url, json={"camera": ORBIT, "quality": "preview"})
        assert image_size(preview.content)[1:] == (32, 32)
        full = client.post(url, json={"camera": ORBIT})
        assert image_size(full.content)[1:] == (45, 45)


# --- the render queue: lanes, deadlines, shutdown -------------------------------------------------


def _hold_the_worker(queue: RenderQueue) -> tuple[threading.Event, object]:
    release = threading.Event()
    blocker = queue.submit(lambda: release.wait(10))
    while queue.running == 0:
        time.sleep(0.002)
    return release, blocker


def test_previews_overtake_queued_full_frames_and_the_capacity_is_shared() -> None:
    queue = RenderQueue(workers=1, queue_size=5, metrics=Metrics())
    order: list[str] = []

    def slow_job(name: str):
        def run() -> str:
            order.append(name)
            time.sleep(0.02)
            return name

        return run

    release, blocker = _hold_the_worker(queue)
    futures = [
        queue.submit(slow_job("full 1"), Lane.FULL),
        queue.submit(slow_job("grid"), Lane.BACKGROUND),
        queue.submit(slow_job("full 2"), Lane.FULL),
        queue.submit(slow_job("preview 1"), Lane.PREVIEW),
        queue.submit(slow_job("preview 2"), Lane.PREVIEW),
    ]
    with pytest.raises(QueueFullError, match="full"):  # 1 running + 5 waiting: every slot taken
        queue.submit(slow_job("one too many"), Lane.PREVIEW)
    futures[2].cancel()  # a queued job dropped gives its slot back
    assert queue.waiting == 4
    futures.append(queue.submit(slow_job("preview 3"), Lane.PREVIEW))
    release.set()
    assert [f.result(5) for f in futures if not f.cancelled()][-1] == "preview 3"
    assert order == ["preview 1", "preview 2", "preview 3", "full 1", "grid"]
    queue.shutdown()
    assert queue.waiting == queue.running == 0


def cooperative_job(cancel: threading.Event, seconds: float = 10.0, log: list[str] | None = None):
    """A fake render that checks ``cancel`` every 5 ms, as the renderer does between chunks; it
    appends how it ended ("stopped" or "finished") to ``log``."""
    log = [] if log is None else log

    def run() -> str:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            if cancel.is_set():
                log.append("stopped")
                raise RenderCancelled("stopped")
            time.sleep(0.005)
        log.append("finished")
        return "finished"

    return run


def test_a_render_past_its_deadline_is_stopped_and_frees_the_worker() -> None:
    metrics = Metrics()
    queue = RenderQueue(workers=1, queue_size=2, metrics=metrics)
    cancel, log = threading.Event(), []
    with pytest.raises(RenderTimeoutError) as timed_out:
        queue.run(cooperative_job(cancel, log=log), timeout=0.2, cancel=cancel)
    assert timed_out.value.started and cancel.is_set()
    assert queue.run(lambda: log.append("next") or 7, timeout=5) == 7
    assert log == ["stopped", "next"]  # the one worker was freed by stopping the job, not by its end
    assert metrics.cancelled._value.get() == 1
    queue.shutdown()


def test_a_render_whose_caller_leaves_is_stopped() -> None:
    queue = RenderQueue(workers=1, queue_size=2, metrics=Metrics())
    cancel, log = threading.Event(), []

    async def leave_early() -> None:
        task = asyncio.create_task(queue.run_async(cooperative_job(cancel, log=log), timeout=30, cancel=cancel))
        while queue.running == 0:
            await asyncio.sleep(0.005)
        task.cancel()  # what a disconnect or a closed stream does to the waiting task
        with pytest.raises(asyncio.CancelledError):
            await task

    # A thread of its own: asyncio.run refuses a thread whose event loop is already running.
    outcome: list[BaseException | None] = []

    def run_loop() -> None:
        try:
            asyncio.run(leave_early())
            outcome.append(None)
        except BaseException as exc:  # handed to the test's thread
            outcome.append(exc)

    runner = threading.Thread(target=run_loop)
    runner.start()
    runner.join(timeout=30)
    assert outcome == [None], outcome
    assert cancel.is_set()
    assert queue.run(lambda: log.append("next") or 8, timeout=5) == 8
    assert log == ["stopped", "next"]
    queue.shutdown()


class _Frames:
    """Stands for a render's tensors: weakly referenceable, to see when it is freed."""


def test_a_jobs_outcome_is_freed_without_the_garbage_collector() -> None:
    """A failed, stopped or finished job's exception or result, and everything its traceback's
    frames hold, is freed by reference counting once its caller is done: no cycle through the
    queue's futures (a server collects cycles rarely, and a cancelled 1440x1440 frame held tens of
    megabytes of tensors)."""
    queue = RenderQueue(workers=1, queue_size=2, metrics=Metrics())
    seen: list[weakref.ref] = []

    def failing() -> None:
        frames = _Frames()  # noqa: F841 - held by the traceback's frame
        seen.append(weakref.ref(frames))
        raise RenderCancelled("stopped")

    def stopping(cancel: threading.Event) -> Callable[[], None]:
        def job() -> None:
            frames = _Frames()
            seen.append(weakref.ref(frames))
            while not cancel.is_set():
                time.sleep(0.005)
            raise RenderCancelled("stopped")
        return job

    def finishing() -> _Frames:
        frames = _Frames()
        seen.append(weakref.ref(frames))
        return frames

    async def wait_async(fn: Callable[[], object], timeout: float, cancel: threading.Event) -> None:
        with contextlib.suppress(RenderCancelled, RenderTimeoutError):
            await queue.run_async(fn, timeout=timeout, cancel=cancel)

    gc.collect()
    gc.disable()
    try:
        with pytest.raises(RenderCancelled):
            queue.run(failing, timeout=5)
        cancel = threading.Event()
        with pytest.raises(RenderTimeoutError):
            queue.run(stopping(cancel), timeout=0.1, cancel=cancel)
        assert queue.run(finishing, timeout=5) is not None
        cancel = threading.Event()

        def both_async() -> None:  # a thread of its own: asyncio.run refuses a thread whose loop runs
            asyncio.run(wait_async(failing, 5.0, threading.Event()))
            asyncio.run(wait_async(stopping(cancel), 0.1, cancel))

        runner = threading.Thread(target=both_async)
        runner.start()
        runner.join(timeout=30)
        assert queue.run(lambda: 0, timeout=5) == 0  # the stopped job has ended
        alive = [ref for ref in seen if ref() is not None]
    finally:
        gc.enable()
        queue.shutdown()
    assert len(seen) == 5
    assert [seen.index(ref) for ref in alive] == []  # by position: run, timed out, finished, async run, async timed out


def test_shutdown_stops_running_renders_and_fails_queued_ones() -> None:
    queue = RenderQueue(workers=1, queue_size=2, metrics=Metrics())
    cancel, log = threading.Event(), []
    running = queue.submit(cooperative_job(cancel, log=log), Lane.FULL, cancel)
    while queue.running == 0:
        time.sleep(0.002)
    queued = queue.submit(lambda: log.append("queued ran") or "never", Lane.PREVIEW)
    queue.shutdown()
    assert log == ["stopped"]  # stopped, not run to its end; the queued one never ran
    assert isinstance(running.exception(1), RenderCancelled)
    assert isinstance(queued.exception(1), QueueFullError)  # its request answers 503
    assert queue.waiting == queue.running == 0
    with pytest.raises(QueueFullError, match="shutting down"):
        queue.submit(lambda: 0)


# --- the server -----------------------------------------------------------------------------------


def test_a_request_past_its_deadline_frees_the_worker_for_the_next(ckpt_dir: Path, tmp_path: Path) -> None:
    """The large frame takes many seconds (tens on a busy 2-core machine); past the limit of 1.5 s
    it is answered 504 and stopped. With one worker, the next request can only be rendered once the
    large one is off it: it is, and the large one never finished. Every pixel is marched
    (``refine_spacing=1``): the tiny field's frame refined from a lattice would end in time."""
    settings = make_settings(
        ckpt_dir, tmp_path / "state", render_timeout_s=1.5, max_full_pixels=BIG_PIXELS, rate_limit_pixels_per_s=0,
        refine_spacing=1,
    )
    with TestClient(create_app(settings)) as client:
        late = client.post("/api/scenes/tiny/render", json={**SMALL, "width": BIG, "height": BIG, "format": "jpeg"})
        assert late.status_code == 504, late.text
        nxt = client.post("/api/scenes/tiny/render", json=SMALL)
        assert nxt.status_code == 200, nxt.text
        metrics = client.get("/metrics").text
        assert FULL_RENDERS_DONE.format(1) in metrics  # the small one only
        assert "visnerf_renders_cancelled_total 1.0" in metrics


def test_the_rate_limit_answers_429_with_retry_after(ckpt_dir: Path, tmp_path: Path) -> None:
    settings = make_settings(
        ckpt_dir, tmp_path / "state", rate_limit_pixels_per_s=100, rate_limit_burst_pixels=5000
    )
    with TestClient(create_app(settings)) as client:
        url = "/api/scenes/tiny/render"
        frame = {"camera": ORBIT, "width": 64, "height": 64}  # 4096 of the 5000
        assert client.post(url, json=frame).status_code == 200
        other_view = {**frame, "camera": {**ORBIT, "azimuth": 31.0}}
        refused = client.post(url, json=other_view)
        assert refused.status_code == 429
        expected = math.ceil((4096 - 904) / 100)  # 32 s, less what refilled meanwhile
        assert int(refused.headers["retry-after"]) in (expected - 1, expected)
        assert "this request costs 4096" in refused.json()["detail"]
        assert client.post(url, json=frame).headers["x-cache"] == "hit"  # a cached frame is free
        preview = {**other_view, "width": 32, "height": 32, "quality": "preview"}  # 1024 x 0.3 = 307
        assert client.post(url, json=preview).status_code == 200  # cheap enough: a preview pixel costs less
        assert client.post(url, json=other_view, headers=AUTH).status_code == 200  # the token's own bucket
        with client.websocket_connect("/api/scenes/tiny/stream") as ws:
            ws.send_text(json.dumps({**frame, "seq": 3, "camera": {**ORBIT, "azimuth": 40.0}, "quality": "full"}))
            error = ws.receive_json()
            assert error["status"] == 429 and error["seq"] == 3 and error["retry_after"] > 1
        assert "visnerf_rate_limited_total 2.0" in client.get("/metrics").text


def test_a_stream_over_its_rate_slows_down_instead_of_failing(ckpt_dir: Path, tmp_path: Path) -> None:
    """A frame whose cost is back within a second waits for it and is rendered."""
    settings = make_settings(ckpt_dir, tmp_path / "state", rate_limit_pixels_per_s=1000, rate_limit_burst_pixels=1100)
    with TestClient(create_app(settings)) as client, client.websocket_connect("/api/scenes/tiny/stream") as ws:
        frame = {"camera": ORBIT, "width": 32, "height": 32, "quality": "full"}  # 1024 of the 1100
        ws.send_text(json.dumps({**frame, "seq": 1}))
        assert ws.receive_json()["seq"] == 1
        ws.receive_bytes()
        ws.send_text(json.dumps({**frame, "seq": 2, "camera": {**ORBIT, "azimuth": 50.0}}))
        header = ws.receive_json()
        assert header["type"] == "frame" and header["seq"] == 2, header
        ws.receive_bytes()
        # it waited for the bucket once, and the frame came (no 429): a wait is no refusal
        metrics = client.get("/metrics").text
        assert "visnerf_stream_rate_waits_total 1.0" in metrics and "visnerf_rate_limited_total 0.0" in metrics


def test_occupancy_grid_builds_run_in_the_render_queue(client: TestClient) -> None:
    renderer = client.app.state.server.registry.get("tiny").renderer
    renderer.field.set_occupancy(torch.ones(8, 8, 8, dtype=torch.bool))  # give it a union grid to narrow
    built_on: list[str] = []
    build = renderer.setting_occupancy.build

    def recording_build(*args, **kwargs):
        built_on.append(threading.current_thread().name)
        return build(*args, **kwargs)

    renderer.setting_occupancy.build = recording_build
    after = renderer.setting_occupancy.cfg.setting_grid_after
    for azimuth in (10.0 * (i + 1) for i in range(after)):  # the after-th frame at one setting starts the build
        body = {**SMALL, "camera": {**ORBIT, "azimuth": azimuth}, "params": {"a": 0.25}}
        assert client.post("/api/scenes/tiny/render", json=body).status_code == 200
    renderer.setting_occupancy.wait()
    assert built_on and built_on[0].startswith("render-")  # a worker of the queue, not a thread beside it
    assert renderer.setting_occupancy.builds == 1


@pytest.mark.slow
def test_a_client_that_leaves_and_a_sigterm_stop_large_renders(ckpt_dir: Path, tmp_path: Path) -> None:
    env = {"VISNERF_MAX_FULL_PIXELS": str(BIG_PIXELS), "VISNERF_RATE_LIMIT_PIXELS_PER_S": "0"}
    big = {"camera": ORBIT, "width": BIG, "height": BIG, "format": "jpeg"}
    with serve_process(ckpt_dir, tmp_path, env) as server:
        url = f"{server.url}/api/scenes/tiny/render"
        # A client that gives up after 0.5 s: the server notices and its render stops.
        with pytest.raises(httpx.ReadTimeout):
            httpx.post(url, json=big, timeout=httpx.Timeout(10.0, read=0.5))
        small = httpx.post(url, json=SMALL, timeout=30)  # one worker: rendered once the large one is off it
        assert small.status_code == 200
        assert FULL_RENDERS_DONE.format(1) in httpx.get(f"{server.url}/metrics").text  # the large one never finished

        # SIGTERM with a large render in flight: it stops at once (503), the process exits within 10 s.
        outcome: list[object] = []

        def large_render() -> None:
            try:
                outcome.append(httpx.post(url, json={**big, "camera": {**ORBIT, "azimuth": 77.0}}, timeout=60))
            except httpx.HTTPError as exc:
                outcome.append(exc)

        deadline = time.monotonic() + 30
        while "visnerf_renders_in_flight 0.0" not in httpx.get(f"{server.url}/metrics").text:
            assert time.monotonic() < deadline, "the abandoned render never let go of its worker"
            time.sleep(0.05)  # the gauge below must count the next render, not the abandoned one
        worker = threading.Thread(target=large_render)
        worker.start()
        deadline = time.monotonic() + 10
        while "visnerf_renders_in_flight 1.0" not in httpx.get(f"{server.url}/metrics").text:
            assert time.monotonic() < deadline, "the large render never started"
            time.sleep(0.05)
        server.process.send_signal(signal.SIGTERM)
        assert server.process.wait(timeout=60) == 0, server.log()
        worker.join(60)
        answer = outcome[0]
        assert isinstance(answer, httpx.Response) and answer.status_code == 503, answer
        assert "shutting down" in answer.json()["detail"] and answer.headers["retry-after"] == "1"
        assert "render queue shut down" in server.log()


def test_a_large_frame_waits_for_the_large_one_running_and_small_ones_pass_it() -> None:
    """Two workers: a large job holds one; a second large job waits (it would run beside it) while
    a small one behind it takes the free worker; the second large job starts once the first ends."""
    queue = RenderQueue(workers=2, queue_size=4, metrics=Metrics())
    release_first = threading.Event()
    first = queue.submit(lambda: release_first.wait(10), Lane.FULL, large=True)
    while queue.running == 0:
        time.sleep(0.002)
    started: list[str] = []
    second = queue.submit(lambda: started.append("large 2") or "large 2", Lane.FULL, large=True)
    small = queue.submit(lambda: started.append("small") or "small", Lane.FULL)
    assert small.result(timeout=5) == "small"
    time.sleep(0.05)
    assert not second.done() and queue.waiting == 1 and started == ["small"]
    release_first.set()
    assert first.result(timeout=5) is True
    assert second.result(timeout=5) == "large 2" and started == ["small", "large 2"]
    # a large job cancelled while it waits gives its slot back, and large jobs run again after
    release_first.clear()
    first = queue.submit(lambda: release_first.wait(10), Lane.FULL, large=True)
    while queue.running == 0:
        time.sleep(0.002)
    dropped = queue.submit(lambda: "never", Lane.FULL, large=True)
    assert dropped.cancel() and queue.waiting == 0
    release_first.set()
    assert queue.submit(lambda: "after", Lane.FULL, large=True).result(timeout=5) == "after"
    queue.shutdown()
    assert queue.waiting == queue.running == 0


def test_a_large_frame_that_would_wait_past_its_limit_is_refused_at_once() -> None:
    """The large jobs ahead of a large job hold it for their estimated seconds (cost times the
    seconds per unit of cost of the large jobs finished so far); one that would then not be done
    within its caller's limit is refused with that wait, not left to time out half drawn."""
    queue = RenderQueue(workers=2, queue_size=4, metrics=Metrics())
    release = threading.Event()
    # before any large job finished there is no estimate: nothing is refused
    held = queue.submit(lambda: release.wait(10), Lane.FULL, large=True, cost=1000.0)
    while queue.running == 0:
        time.sleep(0.002)
    queued = queue.submit(lambda: "queued", Lane.FULL, large=True, cost=100.0, limit_s=0.01)
    release.set()
    assert held.result(timeout=5) is True and queued.result(timeout=5) == "queued"
    # a large job of cost 100 that took 0.2 s: 2 ms per unit, weighted with the two before (faster)
    release.clear()
    assert queue.run(lambda: time.sleep(0.2) or "timed", 5.0, large=True, cost=100.0) == "timed"
    rate = queue._large_rate
    assert rate is not None and 5e-4 < rate < 5e-3
    held = queue.submit(lambda: release.wait(10), Lane.FULL, large=True, cost=5000.0)  # 2.5 s or more
    while queue.running == 0:
        time.sleep(0.002)
    with pytest.raises(WouldOutwaitError, match="not be done within the limit of 1 s") as refused:
        queue.run(lambda: "never", 1.0, large=True, cost=100.0)
    assert 0.8 * 5000 * rate < refused.value.retry_after_s <= 5000 * rate
    assert isinstance(refused.value, QueueFullError)  # a 503 to the caller, its cost refunded
    assert queue.waiting == 0
    # a limit that leaves time for the wait is taken, and so is every small job
    later = queue.submit(lambda: "later", Lane.FULL, large=True, cost=100.0, limit_s=60.0)
    assert queue.run(lambda: "small", 1.0, cost=5000.0) == "small"
    release.set()
    assert held.result(timeout=5) is True and later.result(timeout=5) == "later"
    # a large job with nothing ahead of it is never refused, however long it is estimated to take
    assert queue.run(lambda: "alone", 1.0, large=True, cost=1e9) == "alone"
    queue.shutdown()


def test_a_refused_large_frame_answers_503_with_the_estimated_wait(
    ckpt_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from visnerf_server.frames import FrameRenderer

    async def refuse(self, job, client=None):
        raise WouldOutwaitError(7.2, 30.0)

    monkeypatch.setattr(FrameRenderer, "render_async", refuse)
    with TestClient(create_app(make_settings(ckpt_dir, tmp_path / "state"))) as client:
        answer = client.post("/api/scenes/tiny/render", json={"camera": ORBIT, "width": 64, "height": 64})
    assert answer.status_code == 503 and answer.headers["retry-after"] == "8"
    assert "would wait about 7 s" in answer.json()["detail"]


def test_large_frames_are_full_frames_of_512_by_512_or_more() -> None:
    def job(width: int, height: int, quality: str) -> FrameJob:
        return FrameJob(object(), FrameView(np.eye(4), 40.0, None, width, height, (), quality), "jpeg")  # type: ignore[arg-type]

    assert job(512, 512, quality="full").large and job(1440, 1440, quality="full").large
    assert not job(511, 512, quality="full").large and not job(512, 512, quality="preview").large


def test_a_preview_worker_answers_previews_while_full_frames_hold_the_others() -> None:
    """With the general worker held by a long full frame, a preview runs at once on the preview
    worker; a full frame never does: it waits for the general worker."""
    queue = RenderQueue(workers=1, queue_size=4, metrics=Metrics(), preview_workers=1)
    release, blocker = _hold_the_worker(queue)
    ran_on: dict[str, str] = {}

    def job(name: str):
        def run() -> str:
            ran_on[name] = threading.current_thread().name
            return name

        return run

    full = queue.submit(job("full"), Lane.FULL)
    assert queue.submit(job("preview"), Lane.PREVIEW).result(timeout=5) == "preview"
    assert ran_on["preview"].startswith("render-preview")
    time.sleep(0.05)
    assert not full.done() and queue.waiting == 1  # the preview worker left the full frame alone
    with pytest.raises(QueueFullError):  # capacity: 2 workers and 4 slots, 1 + 1 taken
        for _ in range(5):
            queue.submit(lambda: release.wait(10), Lane.BACKGROUND)
    release.set()
    blocker.result(5)
    assert full.result(timeout=5) == "full" and not ran_on["full"].startswith("render-preview")
    queue.shutdown()
