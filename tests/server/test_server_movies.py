"""Movie jobs: created on the tiny scene, polled to done and downloaded (MP4 decoded with PyAV, GIF
with Pillow); refused over each limit with nothing started; cancelled while running; interactive
renders kept ahead of the job's frames; a scene deleted under a running job."""

import dataclasses
import io
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import av
import pytest
from fastapi.testclient import TestClient
from PIL import Image
from server_helpers import AUTH, ORBIT, UntilCancelledRenderer, make_settings

from visnerf_server.app import create_app
from visnerf_server.registry import Scene
from visnerf_server.render_queue import Lane

FINAL = {"done", "failed", "cancelled"}
PATH = {
    "version": 1,
    "keyframes": [
        {"time": 0.0, "camera": {"azimuth": 0, "elevation": 15, "distance": 2.5, "fov": 30}, "params": {"a": 0.0}},
        {"time": 1.0, "camera": {"azimuth": 90, "elevation": 25, "distance": 2.2, "fov": 30}, "params": {"a": 1.0}},
    ],
}
LONG = {"orbit": 1200, "width": 64, "height": 64, "fps": 30}
"""A job of a few seconds on the tiny scene (each frame about as costly as a 64x64 preview)."""


@contextmanager
def movie_client(ckpt_dir: Path, tmp_path: Path, **overrides: Any) -> Iterator[TestClient]:
    """An app with its movie files under ``tmp_path/movies`` and (unless overridden) no rate limit."""
    values: dict[str, Any] = {"movie_dir": tmp_path / "movies", "rate_limit_pixels_per_s": 0.0, **overrides}
    with TestClient(create_app(make_settings(ckpt_dir, tmp_path / "state", **values))) as client:
        yield client


@pytest.fixture
def movies(ckpt_dir: Path, tmp_path: Path) -> Iterator[TestClient]:
    with movie_client(ckpt_dir, tmp_path) as client:
        yield client


def create(client: TestClient, body: dict[str, Any], scene: str = "tiny") -> dict[str, Any]:
    response = client.post(f"/api/scenes/{scene}/movies", json=body)
    assert response.status_code == 202, response.text
    return response.json()


def poll(client: TestClient, job_id: str, until: set[str] = FINAL, timeout_s: float = 30.0) -> list[dict]:
    """Every status seen until the state is in ``until``."""
    seen: list[dict] = []
    deadline = time.monotonic() + timeout_s
    while True:
        response = client.get(f"/api/movies/{job_id}")
        assert response.status_code == 200, response.text
        seen.append(response.json())
        if seen[-1]["state"] in until:
            return seen
        assert time.monotonic() < deadline, seen[-1]
        time.sleep(0.02)


def wait_running(client: TestClient, job_id: str, frames: int = 2) -> None:
    deadline = time.monotonic() + 20
    while (status := client.get(f"/api/movies/{job_id}").json())["frames_done"] < frames:
        assert status["state"] in {"queued", "running"}, status
        assert time.monotonic() < deadline, status
        time.sleep(0.01)


def preview(client: TestClient, azimuth: float) -> None:
    """One uncached 64x64 preview, answered."""
    body = {"camera": {**ORBIT, "azimuth": azimuth}, "width": 64, "height": 64, "quality": "preview"}
    response = client.post("/api/scenes/tiny/render", json=body)
    assert response.status_code == 200, response.text


def metric(client: TestClient, line_start: str) -> float:
    for line in client.get("/metrics").text.splitlines():
        if line.startswith(line_start + " "):
            return float(line.split()[-1])
    raise AssertionError(f"no metric {line_start}")


def test_mp4_of_a_path_is_rendered_and_downloaded(movies: TestClient) -> None:
    created = create(movies, {"path": PATH, "fps": 12, "width": 48, "height": 32, "format": "mp4"})
    job_id = created["job_id"]
    assert created["status_url"] == f"/api/movies/{job_id}"
    assert created["file_url"] == f"/api/movies/{job_id}/file"
    seen = poll(movies, job_id)
    done = [s["frames_done"] for s in seen]
    assert done == sorted(done), "progress went backwards"
    final = seen[-1]
    assert final["state"] == "done", final
    assert final["frames_done"] == final["frames_total"] == created["frames"] >= 12
    assert final["scene_id"] == "tiny" and final["error"] is None and final["seconds_left"] == 0
    assert final["frames_per_second"] > 0
    response = movies.get(created["file_url"])
    assert response.status_code == 200
    assert response.headers["content-type"] == "video/mp4"
    assert response.headers["content-disposition"] == f'attachment; filename="tiny-{job_id[:8]}.mp4"'
    with av.open(io.BytesIO(response.content)) as container:
        stream = container.streams.video[0]
        frames = list(container.decode(stream))
        assert stream.average_rate == 12
    assert len(frames) == created["frames"]
    assert {(f.width, f.height) for f in frames} == {(48, 32)}
    assert metric(movies, "visnerf_movie_frames_total") == created["frames"]
    assert metric(movies, "visnerf_movie_jobs_started_total") == 1


def test_gif_orbit_and_the_files_go_at_shutdown(ckpt_dir: Path, tmp_path: Path) -> None:
    with movie_client(ckpt_dir, tmp_path, movie_keep_s=0.5) as client:
        created = create(client, {"orbit": 6, "fps": 10, "width": 24, "height": 24, "format": "gif"})
        assert created["frames"] == 6
        assert poll(client, created["job_id"])[-1]["state"] == "done"
        response = client.get(created["file_url"])
        assert response.headers["content-type"] == "image/gif"
        with Image.open(io.BytesIO(response.content)) as gif:
            assert (gif.size, gif.n_frames) == ((24, 24), 6)
        assert len(list((tmp_path / "movies").glob("*/*.gif"))) == 1
        time.sleep(0.6)  # past movie_keep_s: forgotten, file deleted
        gone = client.get(f"/api/movies/{created['job_id']}")
        assert gone.status_code == 404
        assert "do not survive a server restart" in gone.json()["detail"]
        assert list((tmp_path / "movies").glob("*/*")) == []
    assert list((tmp_path / "movies").iterdir()) == []  # the temporary folder went at shutdown


def test_unknown_job_and_bad_requests(movies: TestClient) -> None:
    for method in ("get", "delete"):
        response = getattr(movies, method)("/api/movies/nosuchjob")
        assert response.status_code == 404
        assert "do not survive a server restart" in response.json()["detail"]
    assert movies.get("/api/movies/nosuchjob/file").status_code == 404
    bad = {**PATH, "keyframes": [{**PATH["keyframes"][0], "camera": {**ORBIT, "elevation": 120, "fov": 30}}]}
    response = movies.post("/api/scenes/tiny/movies", json={"path": bad, "width": 32, "height": 32})
    assert response.status_code == 422
    assert "keyframes[0].camera.elevation" in response.json()["detail"]
    both = movies.post("/api/scenes/tiny/movies", json={"path": PATH, "orbit": 4})
    assert both.status_code == 422
    odd = movies.post("/api/scenes/tiny/movies", json={"orbit": 4, "width": 33, "height": 32})
    assert odd.status_code == 422 and "width" in odd.text
    assert movies.post("/api/scenes/nope/movies", json={"orbit": 4}).status_code == 404
    assert metric(movies, "visnerf_movie_jobs_started_total") == 0


def test_each_limit_is_refused_naming_it(ckpt_dir: Path, tmp_path: Path) -> None:
    limits = {"movie_max_frames": 100, "movie_max_pixels": 100 * 32 * 32, "max_image_size": 128}
    limits |= {"movie_jobs_running": 1, "movie_jobs_queued": 1, "movie_jobs_per_client": 5}
    with movie_client(ckpt_dir, tmp_path, **limits) as client:
        cases = [
            ({"orbit": 101, "width": 16, "height": 16}, 413, "limit of 100 frames per job (movie_max_frames)"),
            ({"orbit": 60, "width": 64, "height": 64}, 413, "(movie_max_pixels)"),
            ({"path": {**PATH, "keyframes": [PATH["keyframes"][0], {**PATH["keyframes"][1], "time": 1e9}]},
              "width": 16, "height": 16}, 413, "(movie_max_frames)"),
            ({"orbit": 2, "width": 256, "height": 16}, 422, "width 256 exceeds this server's limit of 128"),
        ]  # fmt: skip
        for body, status, message in cases:
            response = client.post("/api/scenes/tiny/movies", json=body)
            assert (response.status_code, message in response.json()["detail"]) == (status, True), response.text
        assert metric(client, "visnerf_movie_jobs_started_total") == 0
        assert client.app.state.server.queue.running == 0
        first = create(client, {"orbit": 100, "width": 32, "height": 32})
        second = create(client, {"orbit": 100, "width": 32, "height": 32})
        third = client.post("/api/scenes/tiny/movies", json={"orbit": 2, "width": 32, "height": 32})
        assert third.status_code == 429
        assert "limit of 2 movie jobs queued or running" in third.json()["detail"]
        assert int(third.headers["retry-after"]) >= 1
        queued = client.get(second["status_url"]).json()
        assert queued["state"] == "queued"
        assert (queued["frames_done"], queued["frames_per_second"], queued["seconds_left"]) == (0, None, None)
        for job in (second, first):
            assert client.delete(f"/api/movies/{job['job_id']}").status_code == 204
            assert client.get(job["status_url"]).json()["state"] == "cancelled"
        assert metric(client, 'visnerf_movie_jobs_finished_total{state="cancelled"}') == 2


def test_per_client_limit_and_rate_limit(ckpt_dir: Path, tmp_path: Path) -> None:
    budget = {"rate_limit_pixels_per_s": 100.0, "rate_limit_burst_pixels": 10 * 32 * 32}
    with movie_client(ckpt_dir, tmp_path, **budget) as client:
        create(client, {"orbit": 4, "width": 32, "height": 32})  # 4 frames of the bucket's 10
        costly = client.post("/api/scenes/tiny/movies", json={"orbit": 20, "width": 32, "height": 32})
        assert costly.status_code == 429  # priced at the burst: it needs a full bucket
        assert "rate limit" in costly.json()["detail"] and int(costly.headers["retry-after"]) >= 1
    with movie_client(ckpt_dir, tmp_path / "b", movie_jobs_per_client=1) as client:
        first = create(client, {**LONG})
        again = client.post("/api/scenes/tiny/movies", json={"orbit": 2, "width": 32, "height": 32})
        assert again.status_code == 429
        assert "limit of 1 movie jobs queued or running (movie_jobs_per_client)" in again.json()["detail"]
        assert client.delete(f"/api/movies/{first['job_id']}").status_code == 204


def test_cancel_a_running_job_frees_the_worker(movies: TestClient) -> None:
    created = create(movies, LONG)
    job_id = created["job_id"]
    wait_running(movies, job_id)
    assert movies.get(created["file_url"]).status_code == 409
    assert movies.delete(f"/api/movies/{job_id}").status_code == 204
    queue = movies.app.state.server.queue
    assert (queue.running, queue.waiting) == (0, 0)
    status = movies.get(f"/api/movies/{job_id}").json()
    assert status["state"] == "cancelled" and status["frames_done"] < created["frames"]
    file = movies.get(created["file_url"])
    assert file.status_code == 409 and "cancelled" in file.json()["detail"]
    assert list((movies.app.state.server.movies.folder).iterdir()) == []
    preview(movies, 99.0)  # the worker is free: nothing running, nothing waiting (above)
    assert metric(movies, 'visnerf_movie_jobs_finished_total{state="cancelled"}') == 1
    assert movies.delete(f"/api/movies/{job_id}").status_code == 204  # a finished job is forgotten
    assert movies.get(f"/api/movies/{job_id}").status_code == 404


def test_cancel_stops_the_frame_being_rendered(movies: TestClient) -> None:
    registry = movies.app.state.server.registry
    real = registry.get("tiny")
    endless = UntilCancelledRenderer(real.renderer)
    with registry.mutation_lock:
        registry.install(Scene("endless", endless, real.path, "endless-v1"))  # type: ignore[arg-type]
    created = create(movies, {"orbit": 4, "width": 32, "height": 32}, scene="endless")
    poll(movies, created["job_id"], until={"running"})
    deadline = time.monotonic() + 10
    while endless.started == 0:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert movies.delete(created["status_url"]).status_code == 204
    assert (endless.started, endless.stopped) == (1, 1)  # the frame was stopped, not rendered to its end
    assert movies.get(created["status_url"]).json()["state"] == "cancelled"


def test_interactive_renders_keep_priority(movies: TestClient) -> None:
    queue = movies.app.state.server.queue
    real_submit = queue.submit
    lanes: list[Lane] = []
    in_queue: list[int] = []  # movie frames already in the queue when one more was submitted
    outstanding = [0]

    def spy(fn, lane=Lane.FULL, cancel=None, **frame):  # large, cost, limit_s
        lanes.append(lane)
        if lane != Lane.BACKGROUND:
            return real_submit(fn, lane, cancel, **frame)
        in_queue.append(outstanding[0])
        outstanding[0] += 1

        def counted():
            try:
                return fn()
            finally:
                outstanding[0] -= 1  # before the job thread can hear of the result

        return real_submit(counted, lane, cancel)

    queue.submit = spy
    created = create(movies, LONG)
    wait_running(movies, created["job_id"])
    for a in range(7):
        preview(movies, 100.0 + a)
    status = movies.get(created["status_url"]).json()
    assert status["state"] == "running", status  # the job ran all along, the previews beside it
    assert movies.delete(created["status_url"]).status_code == 204
    assert set(lanes) == {Lane.BACKGROUND, Lane.PREVIEW} and len(in_queue) >= 2
    assert max(in_queue) == 0, "a movie frame was queued while another one was in the queue"


@pytest.mark.parametrize("change", ["deleted", "replaced by an upload"])
def test_a_deleted_or_replaced_scene_fails_its_job(movies: TestClient, templates: dict, change: str) -> None:
    created = create(movies, LONG)
    wait_running(movies, created["job_id"])
    if change == "deleted":
        assert movies.delete("/api/scenes/tiny", headers=AUTH).status_code == 204
    else:
        upload = templates["other"].read_bytes()
        assert movies.put("/api/scenes/tiny", content=upload, headers=AUTH).status_code == 200
    final = poll(movies, created["job_id"])[-1]
    assert final["state"] == "failed"
    assert f"scene 'tiny' was {change} while the movie was rendering" in final["error"]
    assert movies.get(created["file_url"]).status_code == 409
    assert metric(movies, 'visnerf_movie_jobs_finished_total{state="failed"}') == 1


def test_openapi_documents_the_movie_routes(movies: TestClient) -> None:
    openapi = movies.get("/openapi.json").json()
    paths = openapi["paths"]
    assert set(paths["/api/scenes/{scene_id}/movies"]) == {"post"}
    assert set(paths["/api/movies/{job_id}"]) == {"get", "delete"}
    assert set(paths["/api/movies/{job_id}/file"]) == {"get"}
    schemas = openapi["components"]["schemas"]
    assert {"path", "orbit", "fps", "width", "height", "format", "quality"} <= set(schemas["MovieRequest"]["properties"])
    assert set(schemas["MovieJobStatus"]["properties"]) == {
        "job_id", "scene_id", "state", "frames_done", "frames_total", "error", "frames_per_second", "seconds_left"
    }  # fmt: skip


def test_disk_budget_deletes_the_oldest_file_first(movies: TestClient) -> None:
    jobs = movies.app.state.server.movies
    small = {"orbit": 4, "width": 32, "height": 32}
    first = create(movies, small)
    assert poll(movies, first["job_id"])[-1]["state"] == "done"
    size = len(movies.get(first["file_url"]).content)
    jobs.limits = dataclasses.replace(jobs.limits, max_disk_bytes=size + size // 2)
    second = create(movies, small)
    assert poll(movies, second["job_id"])[-1]["state"] == "done"
    assert movies.get(first["status_url"]).status_code == 404  # made room for the second
    assert movies.get(second["file_url"]).status_code == 200
    jobs.limits = dataclasses.replace(jobs.limits, max_disk_bytes=size // 2)
    third = poll(movies, create(movies, small)["job_id"])[-1]
    assert third["state"] == "failed" and "(movie_max_disk_bytes)" in third["error"]
    assert movies.get(second["file_url"]).status_code == 200  # kept: the third never fitted
    assert sorted(p.suffix for p in jobs.folder.iterdir()) == [".mp4"]


def test_shutdown_stops_a_running_job_and_removes_the_files(ckpt_dir: Path, tmp_path: Path) -> None:
    with movie_client(ckpt_dir, tmp_path) as client:
        created = create(client, LONG)
        wait_running(client, created["job_id"])
        job = client.app.state.server.movies.get(created["job_id"])
    assert job is not None and job.ended.is_set() and job.frames_done < created["frames"]  # stopped, not finished
    assert list((tmp_path / "movies").iterdir()) == []


def test_the_movie_folder_is_made_by_the_first_job_only(tmp_path: Path) -> None:
    """A server that makes no movie leaves no folder behind, even one stopped without its
    shutdown (a killed process)."""
    from visnerf_server.metrics import Metrics
    from visnerf_server.movie_plans import MovieLimits
    from visnerf_server.movies import MovieJobs
    from visnerf_server.render_queue import RenderQueue

    metrics = Metrics()
    queue = RenderQueue(workers=1, queue_size=2, metrics=metrics)
    limits = MovieLimits(10, 10**6, 1, 1, 1, 60.0, 10**6)
    parent = tmp_path / "movies"
    jobs = MovieJobs(limits, queue, registry=None, metrics=metrics, parent_dir=parent)  # type: ignore[arg-type]
    assert not parent.exists()
    jobs.shutdown()
    assert not parent.exists()
    jobs = MovieJobs(limits, queue, registry=None, metrics=metrics, parent_dir=parent)  # type: ignore[arg-type]
    folder = jobs.folder
    assert folder.is_dir() and folder.parent == parent and jobs.folder == folder
    jobs.shutdown()
    assert not folder.exists()
    queue.shutdown()


@pytest.mark.parametrize(("size", "quality", "large"), [(512, "full", True), (511, "full", False), (512, "preview", False)])
def test_a_full_movie_frame_of_512_by_512_or_more_is_large(size: int, quality: str, large: bool) -> None:
    """Large frames run one at a time in the render queue, a movie's as an interactive one's."""
    from types import SimpleNamespace

    import numpy as np

    from visnerf_server.metrics import Metrics
    from visnerf_server.movie_frames import render_frame
    from visnerf_server.render_queue import RenderQueue

    queue = RenderQueue(workers=1, queue_size=2, metrics=Metrics())
    asked: list[bool] = []
    real_submit = queue.submit

    def spy(fn, lane=Lane.FULL, cancel=None, **frame):
        asked.append(frame.get("large", False))
        return real_submit(fn, lane, cancel, **frame)

    queue.submit = spy
    image = np.zeros((size, size, 3), np.uint8)
    renderer = SimpleNamespace(view=lambda *args: None, setting_grid=lambda view: (None, None),
                               draw=lambda *args: image)
    plan = SimpleNamespace(scene=SimpleNamespace(renderer=renderer),
                           settings=SimpleNamespace(width=size, height=size, quality=quality))
    spec = SimpleNamespace(c2w=None, fov_deg=40.0, params={}, view_height=None)
    assert render_frame(queue, plan, spec, threading.Event()) is image  # type: ignore[arg-type]
    assert asked == [large]
    queue.shutdown()
