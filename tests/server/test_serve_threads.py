"""``visnerf serve``'s options: one per server setting (``settings_options``), ``--threads`` and
``VISNERF_THREADS`` among them (else ``runtime.default_threads``, tested in
tests/model/test_cpu_quota.py)."""

import argparse
import re
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from server_helpers import make_settings

from visnerf_server.app import create_app
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
    # The frames' settings are checked by FramesConfig, which names the field.
    args = parser.parse_args(["serve", "--segment-samples", "32", "--first-segment-samples", "64"])
    assert serve_command(args) == 2
    assert "first_segment_samples (64) must not exceed segment_samples (32)" in capsys.readouterr().err


def test_the_frames_settings_reach_every_scene(ckpt_dir: Path, tmp_path: Path) -> None:
    """``--chunk-rays`` and the setting-grid options become the registry's ``FramesConfig``, which
    every scene it loads renders with."""
    given = given_settings(_parser().parse_args(["serve", "--chunk-rays", "512", "--setting-grids", "0",
                                                 "--setting-grid-after", "3"]))
    with TestClient(create_app(make_settings(ckpt_dir, tmp_path / "state", **given))) as client:
        registry = client.app.state.server.registry
        frames = registry.frames
        assert (frames.chunk_rays, frames.setting_grids, frames.setting_grid_after) == (512, 0, 3)
        assert registry.list() and all(scene.renderer.frames is frames for scene in registry.list())
        assert client.post("/api/scenes/tiny/render", json={"width": 16, "height": 16}).status_code == 200


def test_threads_setting_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("VISNERF_THREADS", "3")
    assert Settings().threads == 3
    monkeypatch.delenv("VISNERF_THREADS")
    assert Settings().threads is None
