"""nginx on loopback in front of ``visnerf serve`` replicas, for ``server_load.py --mode replicas``:
the shipped docker/nginx.conf with its upstream servers and listen port moved to loopback and its
files in a work folder (tests/server/nginx_helpers.py does the same for the tests)."""

import os
import re
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NGINX_CONF = ROOT / "docker" / "nginx.conf"
_UPSTREAM_SERVER = re.compile(r"^(\s*server\s+)server-(\d+):8000(\b[^;\n]*;)\n", re.MULTILINE)


def nginx_binary() -> str | None:
    found = shutil.which("nginx")
    return found if found is not None or not os.access("/usr/sbin/nginx", os.X_OK) else "/usr/sbin/nginx"


def local_conf(upstreams: list[str], port: int, work: Path) -> str:
    """In each upstream block the ``server-1`` line names the first replica, the ``server-2`` line
    (its options kept) each of the others."""

    def replace(match: re.Match[str]) -> str:
        prefix, number, options = match.groups()
        return "".join(f"{prefix}{a}{options}\n" for a in (upstreams[:1] if number == "1" else upstreams[1:]))

    text = _UPSTREAM_SERVER.sub(replace, NGINX_CONF.read_text())
    text = text.replace("listen 8080;", f"listen 127.0.0.1:{port};")
    temp = "".join(
        f"    {name}_temp_path {work / name};\n" for name in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi")
    )
    text = text.replace("http {\n", "http {\n" + temp, 1)
    return text.replace("access_log /dev/stdout;", "access_log off;")


@contextmanager
def running_nginx(upstreams: list[str], port: int, work: Path) -> Iterator[str]:
    """nginx in the foreground; yields its URL, stops it on the way out."""
    binary = nginx_binary()
    if binary is None:
        raise RuntimeError("nginx is not installed (apt-get install nginx)")
    work.mkdir(parents=True, exist_ok=True)
    (work / "nginx.conf").write_text(local_conf(upstreams, port, work))
    log = work / "error.log"
    directives = f"daemon off; pid {work / 'nginx.pid'}; error_log {log} warn;"
    if os.geteuid() == 0:
        directives += " user root;"
    process = subprocess.Popen(
        [binary, "-e", str(log), "-p", str(work), "-c", str(work / "nginx.conf"), "-g", directives]
    )
    try:
        deadline = time.monotonic() + 10
        while True:
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("nginx did not start:\n" + log.read_text(errors="replace"))
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                break
            except OSError:
                time.sleep(0.05)
        yield f"http://127.0.0.1:{port}"
    finally:
        process.terminate()
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
