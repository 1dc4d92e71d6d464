"""``visnerf serve --threads`` and ``VISNERF_THREADS``: the render threads a server is given (else
``runtime.default_threads``, tested in tests/model/test_cpu_quota.py)."""

import argparse

import pytest

from visnerf_server.commands import register


def test_serve_takes_threads() -> None:
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    assert parser.parse_args(["serve", "--threads", "3"]).threads == 3
    assert parser.parse_args(["serve"]).threads is None
    for bad in ("0", "two"):
        with pytest.raises(SystemExit):
            parser.parse_args(["serve", "--threads", bad])


def test_threads_setting_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    from visnerf_server.settings import Settings

    monkeypatch.setenv("VISNERF_THREADS", "3")
    assert Settings().threads == 3
    monkeypatch.delenv("VISNERF_THREADS")
    assert Settings().threads is None
