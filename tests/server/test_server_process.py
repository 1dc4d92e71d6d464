"""The real thing: ``visnerf serve`` in a subprocess on a free loopback port; a frame over HTTP, one
over the WebSocket, an upload with ``visnerf submit``, then SIGTERM and a clean exit (status 0)."""

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from server_helpers import ORBIT, TOKEN, image_size, serve_process
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect


@pytest.fixture
def server(ckpt_dir: Path, tmp_path: Path) -> Iterator[tuple[subprocess.Popen, str, Path]]:
    with serve_process(ckpt_dir, tmp_path) as live:
        yield live.process, live.url, live.log_path


@pytest.mark.slow
def test_serve_http_websocket_submit_and_sigterm(server, templates, tmp_path: Path) -> None:
    proc, url, log_path = server
    health = httpx.get(f"{url}/api/health").json()
    assert health == {"status": "ok", "version": "0.1.0", "scenes": 2, "ready": True}

    frame = httpx.get(f"{url}/api/scenes/tiny/render", params={**ORBIT, "width": 16, "height": 16, "a": 0.3})
    assert frame.status_code == 200
    assert image_size(frame.content) == ("PNG", 16, 16)
    assert float(frame.headers["x-render-time-ms"]) > 0

    ws_url = url.replace("http://", "ws://")
    with connect(f"{ws_url}/api/scenes/tiny/stream") as ws:
        ws.send(
            json.dumps(
                {
                    "seq": 1,
                    "camera": ORBIT,
                    "fov_deg": 30,
                    "width": 16,
                    "height": 16,
                    "params": {"a": 0.3},
                    "quality": "preview",
                    "format": "jpeg",
                }
            )
        )
        header = json.loads(ws.recv(timeout=30))
        assert header["type"] == "frame" and header["seq"] == 1
        data = ws.recv(timeout=30)
        assert isinstance(data, bytes)
        assert image_size(data) == ("JPEG", 16, 16)

    submit = subprocess.run(
        [sys.executable, "-m", "visnerf.cli", "submit", str(templates["still"]), url, "--id", "submitted"],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "VISNERF_TOKEN": TOKEN},
    )
    assert submit.returncode == 0, submit.stderr
    assert "created scene 'submitted'" in submit.stdout
    assert httpx.get(f"{url}/api/scenes/submitted").json()["title"] == "Still"
    refused = subprocess.run(
        [sys.executable, "-m", "visnerf.cli", "submit", str(templates["still"]), url, "--token", "wrong"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert refused.returncode == 1
    assert "403" in refused.stderr and "wrong token" in refused.stderr

    # SIGTERM with a stream still open: graceful shutdown, exit status 0, the stream closed.
    with connect(f"{ws_url}/api/scenes/tiny/stream") as ws:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 0, log_path.read_text()
        with pytest.raises(ConnectionClosed):
            ws.recv(timeout=5)

    log = log_path.read_text()
    access = [json.loads(line) for line in log.splitlines() if line.startswith('{"method"')]
    assert {"method": "GET", "path": "/api/scenes/tiny/render", "status": 200} in [
        {k: e[k] for k in ("method", "path", "status")} for e in access
    ]
    assert TOKEN not in log
    assert "render queue shut down" in log
    assert not list((tmp_path / "checkpoints").glob(".upload-*"))


@pytest.mark.slow
def test_train_submit_uploads_the_trained_checkpoint_to_a_running_server(server, synthetic_scene, tmp_path: Path) -> None:
    _, url, _ = server
    data = synthetic_scene("tangle_static", 16)
    env = {**os.environ, "VISNERF_TOKEN": TOKEN}
    ckpt = tmp_path / "trained.safetensors"
    trained = subprocess.run(
        [sys.executable, "-m", "visnerf.cli", "train", str(data), "--out", str(ckpt), "--iterations", "20", "--quiet",
         "--submit", url],
        capture_output=True, text=True, timeout=300, env=env,
    )
    assert trained.returncode == 0, trained.stderr
    assert "created scene 'trained'" in trained.stdout
    scene = httpx.get(f"{url}/api/scenes/trained").json()
    assert scene["kind"] == "ir" and scene["params"] == []
    frame = httpx.get(f"{url}/api/scenes/trained/render", params={**ORBIT, "width": 16, "height": 16})
    assert frame.status_code == 200 and image_size(frame.content) == ("PNG", 16, 16)
    # A refused upload says so and keeps the checkpoint it trained.
    refused = subprocess.run(
        [sys.executable, "-m", "visnerf.cli", "train", str(data), "--out", str(tmp_path / "again.safetensors"),
         "--iterations", "5", "--quiet", "--submit", url],
        capture_output=True, text=True, timeout=300, env={**os.environ, "VISNERF_TOKEN": "wrong"},
    )
    assert refused.returncode == 1 and "403" in refused.stderr and "saved at" in refused.stderr
    assert (tmp_path / "again.safetensors").is_file()
