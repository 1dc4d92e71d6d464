"""Helpers shared by the server tests (constants, image checks, bad checkpoints, a slow scene, a real
`visnerf serve` process)."""

import io
import os
import pickle
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import torch
from fastapi.testclient import TestClient
from PIL import Image
from safetensors import safe_open
from safetensors.torch import save_file

from visnerf.inference import RenderCancelled, SceneRenderer
from visnerf_server.settings import Settings

TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
ORBIT = {"azimuth": 30.0, "elevation": 20.0, "distance": 2.5}


def make_settings(ckpt_dir: Path, state_dir: Path, **overrides: object) -> Settings:
    values: dict[str, object] = {
        "checkpoints_dir": ckpt_dir,
        "state_dir": state_dir,
        "token": TOKEN,
        "client_dir": None,
        "background_load": False,
    }
    values.update(overrides)
    return Settings(**values)  # type: ignore[arg-type]


def image_size(data: bytes) -> tuple[str, int, int]:
    """(format, width, height) of an encoded image; fails if it does not decode."""
    with Image.open(io.BytesIO(data)) as image:
        image.load()
        return image.format, image.width, image.height


def listing(folder: Path) -> list[str]:
    """Every entry of a folder, hidden ones included."""
    return sorted(p.name for p in folder.iterdir())


def scene_ids(client: TestClient) -> list[str]:
    return [s["id"] for s in client.get("/api/scenes").json()]


# --- bad checkpoints -------------------------------------------------------------------------


def _tensors_and_meta(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    with safe_open(str(path), "pt") as f:
        return {k: f.get_tensor(k) for k in f.keys()}, dict(f.metadata())


def pickle_checkpoint(path: Path) -> Path:
    """A pickle (what torch.save writes) renamed to .safetensors."""
    with path.open("wb") as f:
        pickle.dump({"density": torch.zeros(4)}, f)
    return path


def truncated_checkpoint(good: Path, path: Path) -> Path:
    data = good.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])
    return path


def wrong_shape_checkpoint(good: Path, path: Path) -> Path:
    tensors, meta = _tensors_and_meta(good)
    tensors["density_grid.planes.0"] = torch.zeros(4, 9, 9)
    save_file(tensors, str(path), metadata=meta)
    return path


def nan_checkpoint(good: Path, path: Path) -> Path:
    tensors, meta = _tensors_and_meta(good)
    broken = tensors["color_decoder.hidden.weight"].clone()
    broken[0, 0] = float("nan")
    tensors["color_decoder.hidden.weight"] = broken
    save_file(tensors, str(path), metadata=meta)
    return path


class SlowRenderer:
    """Wraps a real scene; every render first sleeps (to make queues and stale frames observable)."""

    def __init__(self, inner: SceneRenderer, delay_s: float) -> None:
        self.inner = inner
        self.info = inner.info
        self.delay_s = delay_s
        self.calls = 0

    def __getattr__(self, name: str):  # view, setting_grid, ... of the real scene
        return getattr(self.inner, name)

    def draw(self, *args, **kwargs) -> np.ndarray:
        self.calls += 1
        time.sleep(self.delay_s)
        return self.inner.draw(*args, **kwargs)


class UntilCancelledRenderer:
    """Wraps a real scene; a frame of at least ``min_pixels`` "renders" until its cancel check says
    stop (or 20 s), counting ``started`` and ``stopped`` (``began`` is set at each start); smaller
    frames render at once."""

    def __init__(self, inner: SceneRenderer, min_pixels: int = 0) -> None:
        self.inner = inner
        self.info = inner.info
        self.min_pixels = min_pixels
        self.started = 0
        self.stopped = 0
        self.began = threading.Event()

    def __getattr__(self, name: str):  # view, setting_grid, ... of the real scene
        return getattr(self.inner, name)

    def draw(self, view, own=None, cancel=None) -> np.ndarray:
        if view.width * view.height >= self.min_pixels:
            self.started += 1
            self.began.set()
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                if cancel is not None and cancel():
                    self.stopped += 1
                    raise RenderCancelled("render cancelled")
                time.sleep(0.005)
        return self.inner.draw(view, own, cancel)


# --- a real server process ---------------------------------------------------------------------


@dataclass
class LiveServer:
    """A running ``visnerf serve``: the process, its base URL and the file its output goes to."""

    process: subprocess.Popen
    url: str
    log_path: Path

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_ready(server: LiveServer, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        assert server.process.poll() is None, server.log()
        try:
            if httpx.get(f"{server.url}/api/ready", timeout=2).status_code == 200:
                return
        except httpx.TransportError:
            pass
        assert time.monotonic() < deadline, "server did not become ready:\n" + server.log()
        time.sleep(0.1)


@contextmanager
def serve_process(
    ckpt_dir: Path,
    work_dir: Path,
    env: dict[str, str] | None = None,
    ready_timeout_s: float = 60.0,
    port: int | None = None,
) -> Iterator[LiveServer]:
    """``visnerf serve --no-client`` on ``ckpt_dir`` in a subprocess, on a free loopback port, with the
    test token and its state in ``work_dir/state``; its output goes to ``work_dir/server.log``.
    Yields once ``/api/ready`` answers 200; kills the process on the way out if it still runs.
    ``VISNERF_*`` variables of the caller's environment are not passed on; ``env`` adds some.
    ``port``: that one instead of a free one (a server restarted where it was)."""
    port = free_port() if port is None else port
    log_path = work_dir / "server.log"
    inherited = {k: v for k, v in os.environ.items() if not k.startswith("VISNERF_")}
    full_env = {**inherited, "VISNERF_TOKEN": TOKEN, "VISNERF_STATE_DIR": str(work_dir / "state"), **(env or {})}
    command = [sys.executable, "-m", "visnerf.cli", "serve", "--port", str(port), "--checkpoints", str(ckpt_dir),
               "--no-client"]  # fmt: skip
    with log_path.open("wb") as log:
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=full_env)
    server = LiveServer(process, f"http://127.0.0.1:{port}", log_path)
    try:
        _wait_ready(server, ready_timeout_s)
        yield server
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(10)
