"""Which browser origins may open a stream: the server's own (``Origin`` naming the ``Host`` the
request came to) and those in ``Settings.allowed_origins``. A WebSocket handshake is not covered
by the browser's same-origin policy, so without this any page could drive the server through a
visitor's browser."""

from collections.abc import Collection
from urllib.parse import urlsplit

DEFAULT_PORTS = {"http": 80, "https": 443, "ws": 80, "wss": 443}


def normalize_origin(origin: str) -> str:
    """``scheme://host[:port]`` in lower case, without a default port or a trailing slash; raises
    ValueError for anything else (a path, a query, credentials, an unknown scheme)."""
    text = origin.strip().rstrip("/").lower()
    if text == "null":  # sandboxed frames and file:// pages
        return text
    parts = urlsplit(text)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"origin {origin!r} must be http(s)://host[:port]")
    if parts.path or parts.query or parts.fragment or parts.username is not None:
        raise ValueError(f"origin {origin!r} must be http(s)://host[:port], nothing after the port")
    try:
        port = parts.port
    except ValueError:
        raise ValueError(f"origin {origin!r} has an invalid port") from None
    return f"{parts.scheme}://{_host_port(parts.netloc, port, parts.scheme)}"


def _host_port(netloc: str, port: int | None, scheme: str) -> str:
    """``netloc`` without the scheme's default port."""
    if port is not None and port == DEFAULT_PORTS.get(scheme):
        return netloc.rsplit(":", 1)[0]
    return netloc


def _same_host(origin: str, host: str) -> bool:
    """Whether ``origin`` (normalised) names ``host`` (a Host header, port optional)."""
    scheme, _, netloc = origin.partition("://")
    host = host.strip().lower()
    try:
        port = urlsplit(f"//{host}").port
    except ValueError:
        return False
    return _host_port(host, port, scheme) == netloc


def origin_allowed(origin: str | None, host: str | None, allowed: Collection[str]) -> bool:
    """No ``Origin`` (a client that is not a browser), the server's own, or an allowed one."""
    if origin is None:
        return True
    try:
        normalized = normalize_origin(origin)
    except ValueError:
        return False
    if normalized in allowed:
        return True
    return normalized != "null" and host is not None and _same_host(normalized, host)
