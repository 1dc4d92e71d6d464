"""``visnerf serve``'s options: one per server setting (``settings_options``), ``--threads`` and
``VISNERF_THREADS`` among them (else ``runtime.default_threads``, tested in
tests/model/test_cpu_quota.py)."""

import argparse
import re
from pathlib import Path

import pytest

from visnerf_server.commands import register, serve_command
from visnerf_server.settings import Settings
from visnerf_server.settings_options import HAND_WRITTEN, NOT_OPTIONS, given_settings


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    return parser


def test_every_setting_is_an_option_or_says_why_not() -> None:
    text = _parser()._subparsers._group_actions[0].choices["serve"].format_help()  # type: ignore[union-attr]
    for name in Settings.model_fields:
        option = HAND_WRITTEN.get(name, "--" + name.replace("_", "-"))
        offered = re.search(re.escape(option) + r"[\s\]]", text) is not None
        assert offered != (name in NOT_OPTIONS), name
    assert re.search(r"--token[\s\]]", text) is None  # a command line is visible to every user of the machine


def test_given_options_become_settings_and_the_others_stay_unset() -> None:
    args = _parser().parse_args(["serve", "--threads", "3", "--render-queue-size", "4", "--allowed-origins",
                                 "https://a.example,https://b.example", "--no-warmup", "--log-format", "text",
                                 "--movie-dir", "/tmp/movies", "--preview-pixel-cost", "0.5"])
    given = given_settings(args)
    assert given == {"threads": 3, "render_queue_size": 4, "allowed_origins": ("https://a.example", "https://b.example"),
                     "warmup": False, "log_format": "text", "movie_dir": Path("/tmp/movies"), "preview_pixel_cost": 0.5}
    settings = Settings(**given)
    assert settings.allowed_origins == ("https://a.example", "https://b.example") and settings.render_queue_size == 4
    assert given_settings(_parser().parse_args(["serve"])) == {}


def test_a_value_of_the_wrong_kind_or_out_of_range_is_refused_naming_the_option(capsys) -> None:
    parser = _parser()
    for bad in (["--threads", "two"], ["--log-format", "xml"]):
        with pytest.raises(SystemExit):
            parser.parse_args(["serve", *bad])
    args = parser.parse_args(["serve", "--threads", "0", "--jpeg-quality", "101"])
    assert serve_command(args) == 2
    err = capsys.readouterr().err
    assert "--threads" in err and "--jpeg-quality" in err


def test_threads_setting_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("VISNERF_THREADS", "3")
    assert Settings().threads == 3
    monkeypatch.delenv("VISNERF_THREADS")
    assert Settings().threads is None
