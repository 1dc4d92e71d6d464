"""Behind a proxy (``Settings.trusted_proxies``): the rate limit keys on the client named in
``X-Forwarded-For`` when, and only when, the request comes from a trusted proxy."""

import itertools
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError
from server_helpers import make_settings

from visnerf_server.app import create_app
from visnerf_server.settings import Settings

FRAME = 16
"""A full-quality 16x16 frame costs 256 pixels: a bucket of 256 holds one."""
_views = itertools.count()


def render_status(client: TestClient, forwarded_for: str | None) -> int:
    """A frame from a new view (cache hits are free), sent with that ``X-Forwarded-For``."""
    headers = {} if forwarded_for is None else {"X-Forwarded-For": forwarded_for}
    params = {"azimuth": next(_views) % 170, "width": FRAME, "height": FRAME, "quality": "full"}
    return client.get("/api/scenes/tiny/render", params=params, headers=headers).status_code


def limited_client(ckpt_dir: Path, tmp_path: Path, peer: str, trusted: tuple[str, ...]) -> TestClient:
    settings = make_settings(
        ckpt_dir,
        tmp_path / "state",
        trusted_proxies=trusted,
        rate_limit_pixels_per_s=1.0,
        rate_limit_burst_pixels=FRAME * FRAME,
        store_poll_s=0.0,
    )
    return TestClient(create_app(settings), client=(peer, 40000))


def test_a_trusted_proxy_names_the_client(ckpt_dir: Path, tmp_path: Path) -> None:
    with limited_client(ckpt_dir, tmp_path, "127.0.0.1", ("127.0.0.1",)) as client:
        assert render_status(client, "203.0.113.1") == 200
        assert render_status(client, "203.0.113.1") == 429  # that client's bucket is empty
        assert render_status(client, "203.0.113.2") == 200  # another client behind the same proxy
        # A client cannot pick its key: the proxy appends the address it saw, and that one counts.
        assert render_status(client, "203.0.113.9, 203.0.113.1") == 429


def test_trusted_networks_are_skipped_from_the_right(ckpt_dir: Path, tmp_path: Path) -> None:
    with limited_client(ckpt_dir, tmp_path, "10.0.0.5", ("10.0.0.0/8",)) as client:
        assert render_status(client, "203.0.113.1, 10.0.0.7") == 200  # two proxies of the network
        assert render_status(client, "203.0.113.1") == 429


@pytest.mark.parametrize("trusted", [(), ("127.0.0.1",)], ids=["nobody-trusted", "another-peer-trusted"])
def test_forwarded_for_from_an_untrusted_peer_is_ignored(ckpt_dir: Path, tmp_path: Path, trusted: tuple) -> None:
    with limited_client(ckpt_dir, tmp_path, "192.0.2.7", trusted) as client:
        assert render_status(client, "203.0.113.1") == 200
        assert render_status(client, "203.0.113.2") == 429  # the same peer, whatever it claims


def test_trusted_proxies_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("VISNERF_TRUSTED_PROXIES", " 127.0.0.1, 10.0.0.0/8 ,::1")
    monkeypatch.setenv("VISNERF_STORE_POLL_S", "0.5")
    settings = Settings()
    assert settings.trusted_proxies == ("127.0.0.1", "10.0.0.0/8", "::1")
    assert settings.store_poll_s == 0.5
    assert Settings(trusted_proxies="*").trusted_proxies == ("*",)
    assert Settings.model_fields["trusted_proxies"].default == ()
    with pytest.raises(ValidationError, match="nginx"):
        Settings(trusted_proxies="nginx")  # a name, not an address: refused, not silently ignored
    with pytest.raises(ValidationError):
        Settings(store_poll_s=-1)
