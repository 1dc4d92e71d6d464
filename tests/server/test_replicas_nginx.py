"""Two real ``visnerf serve`` replicas on one checkpoints folder behind real nginx running the
shipped docker/nginx.conf (upstreams and port moved to loopback): uploads, replacements and
deletions through nginx reach both replicas (each asked directly), renders through nginx keep
answering while a replica is stopped and started again, and the stream's WebSocket upgrade and
Origin check work through the proxy."""

import itertools
import json
import shutil
import signal
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
from nginx_helpers import nginx_binary, running_nginx
from required_tools import skip_unless_present
from server_helpers import AUTH, LiveServer, free_port, image_size, serve_process
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

REPO = Path(__file__).resolve().parents[2]
BUNDLED = REPO / "checkpoints" / "tangle_iso.safetensors"
"""The smallest bundled checkpoint: the store both replicas start from."""
REPLICA_ENV = {
    "VISNERF_STORE_POLL_S": "0.1",
    "VISNERF_TRUSTED_PROXIES": "127.0.0.1",
    "VISNERF_THREADS": "1",  # two replicas, nginx and the test share the machine's cores
}
PROPAGATION_TIMEOUT_S = 15.0
RENDER_LOG_LINE = '"method": "GET", "path": "/api/scenes/tangle_iso/render", "status": 200'
"""A render answered, in a replica's access log."""
RENDER = {"azimuth": 30.0, "elevation": 20.0, "width": 24, "height": 24, "quality": "preview", "format": "jpeg"}

NGINX = nginx_binary()


@pytest.fixture(autouse=True, scope="module")
def _needs_nginx() -> None:
    skip_unless_present("nginx", NGINX is not None, "nginx is not installed (scripts/test.sh installs it as root)")


def wait_for(condition: Callable[[], bool], what: str, timeout_s: float = PROPAGATION_TIMEOUT_S) -> float:
    """Seconds until ``condition()`` held; fails after ``timeout_s``."""
    start = time.monotonic()
    while not condition():
        assert time.monotonic() - start < timeout_s, f"not within {timeout_s} s: {what}"
        time.sleep(0.05)
    return time.monotonic() - start


def version_on(server: LiveServer, scene_id: str) -> str | None:
    """The scene's version as the replica serves it; None when it answers otherwise than 200."""
    response = httpx.get(f"{server.url}/api/scenes/{scene_id}", timeout=10)
    return response.json()["version"] if response.status_code == 200 else None


@dataclass
class Cluster:
    replicas: list[LiveServer]
    url: str
    """nginx's."""
    store: Path
    work: Path
    stack: ExitStack
    """Holds the processes: a replica started again joins it."""


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    """Two replicas on one store folder (a copy of a bundled checkpoint), started side by side,
    behind nginx; one set for the module (starting them is most of its time)."""
    work = tmp_path_factory.mktemp("replicas")
    store = work / "store"
    store.mkdir()
    shutil.copy(BUNDLED, store / BUNDLED.name)
    with ExitStack() as stack, ThreadPoolExecutor(2) as pool:
        ports = [free_port(), free_port()]
        starting = []
        for i, port in enumerate(ports):
            (work / f"replica-{i}").mkdir()
            starting.append(serve_process(store, work / f"replica-{i}", REPLICA_ENV, 90.0, port))
        futures = [pool.submit(s.__enter__) for s in starting]
        replicas = []
        for server, future in zip(starting, futures, strict=True):
            replicas.append(future.result())
            stack.push(server)  # its __exit__ stops it
        url = stack.enter_context(running_nginx(NGINX, [f"127.0.0.1:{p}" for p in ports], free_port(), work / "nginx"))  # type: ignore[arg-type]
        yield Cluster(replicas, url, store, work, stack)


@pytest.mark.slow
def test_uploads_and_deletes_through_nginx_reach_every_replica(cluster: Cluster, templates: dict[str, Path]) -> None:
    replicas, url, store = cluster.replicas, cluster.url, cluster.store
    with httpx.Client(base_url=url, timeout=30) as proxy:
        created = proxy.put("/api/scenes/shared", content=templates["tiny"].read_bytes(), headers=AUTH)
        assert created.status_code == 201, created.text
        version = created.json()["version"]
        for replica in replicas:
            wait_for(lambda r=replica: version_on(r, "shared") == version, f"{replica.url} serves the upload")
        frame = proxy.get("/api/scenes/shared/render", params={**RENDER, "a": 0.5})
        assert frame.status_code == 200 and image_size(frame.content) == ("JPEG", 24, 24)

        replaced = proxy.put("/api/scenes/shared", content=templates["other"].read_bytes(), headers=AUTH)
        assert replaced.status_code == 200, replaced.text
        new_version = replaced.json()["version"]
        assert new_version != version
        for replica in replicas:
            wait_for(lambda r=replica: version_on(r, "shared") == new_version, f"{replica.url} serves the replacement")

        assert proxy.delete("/api/scenes/shared", headers=AUTH).status_code == 204
        for replica in replicas:
            wait_for(
                lambda r=replica: httpx.get(f"{r.url}/api/scenes/shared").status_code == 404,
                f"{replica.url} drops the deleted scene",
            )
        assert [s["id"] for s in proxy.get("/api/scenes").json()] == ["tangle_iso"]
    for replica in replicas:
        assert httpx.get(f"{replica.url}/api/ready").json()["failed"] == {}
    assert sorted(p.name for p in store.iterdir()) == ["tangle_iso.safetensors"]  # no temporary left


def test_the_stream_works_through_nginx(cluster: Cluster) -> None:
    url = cluster.url
    ws_url = url.replace("http://", "ws://") + "/api/scenes/tangle_iso/stream"
    message = {"seq": 1, "camera": {"azimuth": 10, "elevation": 10, "distance": 3}, "fov_deg": 40, "width": 16,
               "height": 16, "params": {}, "quality": "preview", "format": "jpeg"}  # fmt: skip
    # A browser on the proxy's address: its Origin names the Host nginx passes on (port included).
    with connect(ws_url, origin=url, proxy=None) as ws:  # type: ignore[arg-type]
        ws.send(json.dumps(message))
        header = json.loads(ws.recv(timeout=30))
        assert header["type"] == "frame" and header["seq"] == 1, header
        assert image_size(ws.recv(timeout=30)) == ("JPEG", 16, 16)
    with pytest.raises(InvalidStatus) as refused:
        connect(ws_url, origin="http://elsewhere.example", proxy=None)  # type: ignore[arg-type]
    assert refused.value.response.status_code == 403


@pytest.mark.slow
def test_renders_keep_answering_while_a_replica_restarts(cluster: Cluster) -> None:
    """Last in the module: it replaces the first replica."""
    replicas, url = cluster.replicas, cluster.url
    answers: list[tuple[int, str | None]] = []
    failures: list[str] = []
    done = threading.Event()

    def load() -> None:
        with httpx.Client(base_url=url, timeout=40) as proxy:
            for i in itertools.count():
                if done.is_set():
                    return
                view = {"azimuth": i * 7.3 % 360 - 180, "elevation": i * 3.1 % 120 - 60}  # few cache answers
                try:
                    response = proxy.get("/api/scenes/tangle_iso/render", params={**RENDER, **view})
                    answers.append((response.status_code, response.headers.get("retry-after")))
                except httpx.HTTPError as exc:  # what a client of the proxy must never see
                    failures.append(repr(exc))

    client = threading.Thread(target=load)
    client.start()
    try:
        wait_for(lambda: len(answers) >= 3, "renders through nginx")
        stopped = replicas[0]
        stopped.process.send_signal(signal.SIGTERM)
        assert stopped.process.wait(20) == 0, stopped.log()
        during = len(answers)
        wait_for(lambda: len(answers) >= during + 3, "renders with one replica down")
        port = int(stopped.url.rsplit(":", 1)[1])
        (cluster.work / "replica-0-again").mkdir()
        again = serve_process(cluster.store, cluster.work / "replica-0-again", REPLICA_ENV, 90.0, port)
        restarted = cluster.stack.enter_context(again)
        wait_for(lambda: RENDER_LOG_LINE in restarted.log(), "nginx sends renders to the restarted replica", 30.0)
        after = len(answers)
        wait_for(lambda: len(answers) >= after + 3, "renders after the restart")
    finally:
        done.set()
        client.join(60)
    assert not failures, failures
    assert answers and all(status == 200 or (status == 503 and retry) for status, retry in answers), answers
    assert sum(status == 200 for status, _ in answers) >= len(answers) - 2
