"""Browser tests of the web client: the real server in a subprocess, driven by headless Chromium.

The session server loads copies of the bundled checkpoints (``vortex_tf1``: DVR with two opacity
axes; ``tangle_iso``: IR with one isovalue axis), as a user's server would. Each test gets a fresh page and leaves a screenshot in ``tests/_artifacts/``.
Skipped when Playwright or a Chromium binary is missing (``VISNERF_CHROMIUM`` overrides the path).
"""

import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from client_helpers import ARTIFACTS
from required_tools import skip_unless_present

REPO = Path(__file__).resolve().parents[2]
CHROMIUM = os.environ.get("VISNERF_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
VIEWPORT = {"width": 1280, "height": 800}
BUNDLED = ("vortex_tf1", "tangle_iso")
READY_TIMEOUT_S = 60.0


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class ServerProcess:
    process: subprocess.Popen
    base_url: str
    log_path: Path

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=5)


def start_server(checkpoints: Path, name: str, port: int | None = None) -> ServerProcess:
    """``visnerf serve`` on a loopback port (a free one by default); returns once GET /api/ready
    answers 200."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    port = port or free_port()
    log_path = ARTIFACTS / f"server-{name}.log"
    log = log_path.open("a")
    cmd = [
        sys.executable, "-m", "visnerf.cli", "serve",
        "--host", "127.0.0.1", "--port", str(port), "--checkpoints", str(checkpoints),
    ]  # fmt: skip
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    process = subprocess.Popen(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, env=env)
    server = ServerProcess(process, f"http://127.0.0.1:{port}", log_path)
    deadline = time.monotonic() + READY_TIMEOUT_S
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"server exited with {process.returncode}:\n{log_path.read_text()[-3000:]}")
        try:
            with urllib.request.urlopen(f"{server.base_url}/api/ready", timeout=2) as response:
                if response.status == 200:
                    return server
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            pass
        time.sleep(0.2)
    server.stop()
    raise RuntimeError(f"server not ready after {READY_TIMEOUT_S} s:\n{log_path.read_text()[-3000:]}")


@pytest.fixture(scope="session")
def checkpoints_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Copies of the bundled checkpoints (tests may upload or delete; the repository's stay as they are)."""
    directory = tmp_path_factory.mktemp("checkpoints")
    for name in BUNDLED:
        source = REPO / "checkpoints" / f"{name}.safetensors"
        if not source.is_file():
            raise FileNotFoundError(f"bundled checkpoint {source} is missing (scripts/train_bundled.sh makes it)")
        shutil.copy2(source, directory / source.name)
    return directory


@pytest.fixture(scope="session")
def server(checkpoints_dir: Path) -> Iterator[ServerProcess]:
    proc = start_server(checkpoints_dir, "session")
    yield proc
    proc.stop()


@pytest.fixture(scope="session")
def base_url(server: ServerProcess) -> str:
    return server.base_url


@pytest.fixture(scope="package")
def browser() -> Iterator[object]:
    """One Chromium for the client tests, closed when they end: Playwright's sync API keeps an
    event loop running in the main thread while it is open, which later tests may not expect."""
    playwright_sync = pytest.importorskip("playwright.sync_api")
    skip_unless_present("chromium", Path(CHROMIUM).exists(), f"no Chromium at {CHROMIUM} (set VISNERF_CHROMIUM)")
    with playwright_sync.sync_playwright() as p:
        instance = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield instance
        instance.close()


@pytest.fixture
def page(browser, request: pytest.FixtureRequest) -> Iterator[object]:
    """A fresh page; page errors fail the test; a screenshot is saved when the test ends. The
    page keeps to server frames (the user's "Server frames only" choice, kept in localStorage),
    as the tests of the server path expect; a test marked ``local_frames`` gets the page as a
    user first sees it, drawing camera moves from bakes."""
    context = browser.new_context(viewport=VIEWPORT, accept_downloads=True)
    if request.node.get_closest_marker("local_frames") is None:
        context.add_init_script("try { localStorage.setItem('visnerf.serverFrames', '1'); } catch (e) {}")
    pg = context.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda exc: errors.append(str(exc)))
    pg.set_default_timeout(15_000)
    yield pg
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    try:
        pg.screenshot(path=str(ARTIFACTS / f"{request.node.name}.png"))
    finally:
        context.close()
    assert not errors, f"uncaught errors in the page: {errors}"


@pytest.fixture
def extra_server(checkpoints_dir: Path) -> Iterator[object]:
    """Start a server of the test's own (e.g. one the test will stop); stopped at teardown."""
    started: list[ServerProcess] = []

    def start(name: str, port: int | None = None) -> ServerProcess:
        proc = start_server(checkpoints_dir, name, port)
        started.append(proc)
        return proc

    yield start
    for proc in started:
        proc.stop()
