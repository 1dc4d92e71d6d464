"""Real nginx on loopback with the shipped docker/nginx.conf: its upstream servers and listen port
replaced by loopback ones, its files (pid, logs, temporaries) in a work folder. Used by
``server_load.py --mode replicas`` and by tests/server/test_replicas_nginx.py."""

import os
import re
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
NGINX_CONF = REPO / "docker" / "nginx.conf"
_UPSTREAM_SERVER = re.compile(r"^(\s*server\s+)server-(\d+):8000(\b[^;\n]*;)\n", re.MULTILINE)
TEMP_PATHS = ("client_body", "proxy", "fastcgi", "uwsgi", "scgi")


def nginx_binary() -> str | None:
    """nginx on PATH, or Debian's /usr/sbin/nginx (not on a user's PATH)."""
    found = shutil.which("nginx")
    if found is None and os.access("/usr/sbin/nginx", os.X_OK):
        found = "/usr/sbin/nginx"
    return found


def local_nginx_conf(upstreams: list[str], listen_port: int, work_dir: Path, template: Path = NGINX_CONF) -> str:
    """The shipped configuration balancing ``upstreams`` (``host:port``) on 127.0.0.1:``listen_port``:
    in each upstream block, the ``server-1`` line for the first and the ``server-2`` line (its
    options kept) for each of the others."""

    def replace(match: re.Match[str]) -> str:
        prefix, number, options = match.groups()
        addresses = upstreams[:1] if number == "1" else upstreams[1:]
        return "".join(f"{prefix}{address}{options}\n" for address in addresses)

    text, found = _UPSTREAM_SERVER.subn(replace, template.read_text())
    if not found:
        raise RuntimeError(f"no `server server-N:8000 ...;` line in {template}")
    text, listens = re.subn(r"listen 8080;", f"listen 127.0.0.1:{listen_port};", text)
    if listens != 1:
        raise RuntimeError(f"no `listen 8080;` in {template}")
    temp = "".join(f"    {name}_temp_path {work_dir / name};\n" for name in TEMP_PATHS)
    text = text.replace("http {\n", "http {\n" + temp, 1)
    return text.replace("access_log /dev/stdout;", f"access_log {work_dir / 'access.log'};")


def _wait_listening(port: int, process: subprocess.Popen, log: Path, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        if process.poll() is not None:
            raise RuntimeError("nginx exited:\n" + log.read_text(errors="replace"))
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise RuntimeError("nginx is not listening:\n" + log.read_text(errors="replace")) from None
            time.sleep(0.05)


@contextmanager
def running_nginx(binary: str, upstreams: list[str], listen_port: int, work_dir: Path) -> Iterator[str]:
    """nginx in the foreground on the shipped configuration; yields its base URL, stops it with
    SIGQUIT (graceful) or kills it on the way out. Its error log is ``work_dir/error.log``."""
    work_dir.mkdir(parents=True, exist_ok=True)
    conf = work_dir / "nginx.conf"
    conf.write_text(local_nginx_conf(upstreams, listen_port, work_dir))
    error_log = work_dir / "error.log"
    directives = f"daemon off; pid {work_dir / 'nginx.pid'}; error_log {error_log} warn;"
    if os.geteuid() == 0:  # workers would run as nobody, who cannot enter pytest's 0700 folders
        directives += " user root;"
    command = [binary, "-e", str(error_log), "-p", str(work_dir), "-c", str(conf), "-g", directives]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    try:
        _wait_listening(listen_port, process, error_log)
        yield f"http://127.0.0.1:{listen_port}"
    finally:
        process.terminate()  # SIGTERM: fast shutdown
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(10)
