"""Training and evaluation need the ``train`` extra (scikit-image, matplotlib), which a server install
leaves out: those sub-commands say so before they start, and the others do not ask for it."""

import argparse
from pathlib import Path

import pytest

from visnerf import cli


def test_missing_modules_names_only_what_is_absent() -> None:
    args = argparse.Namespace(requires=("json", "no_such_module_for_visnerf"))
    assert cli.missing_modules(args) == ["no_such_module_for_visnerf"]
    assert cli.missing_modules(argparse.Namespace()) == []


@pytest.mark.parametrize(
    ("argv", "requires"),
    [
        (["train", "data", "--out", "m.safetensors"], ("skimage",)),
        (["eval", "m.safetensors", "data", "--out", "report"], ("skimage", "matplotlib")),
        (["serve"], ()),
        (["submit", "m.safetensors", "http://127.0.0.1:8000"], ()),
        (["render", "m.safetensors", "-o", "f.png"], ()),
        (["make-scene", "tangle_iso", "--out", "data"], ()),
    ],
)
def test_only_training_and_evaluation_ask_for_the_train_extra(argv: list[str], requires: tuple[str, ...]) -> None:
    args = cli.build_parser().parse_args(argv)
    assert getattr(args, "requires", ()) == requires


def test_a_command_whose_extra_is_missing_stops_before_it_starts(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    monkeypatch.setattr(cli, "missing_modules", lambda args: ["skimage", "matplotlib"])
    report = tmp_path / "report"
    assert cli.main(["eval", str(tmp_path / "m.safetensors"), str(tmp_path), "--out", str(report)]) == 2
    err = capsys.readouterr().err
    assert "visnerf eval needs skimage, matplotlib" in err and "pip install 'visnerf[train]'" in err
    assert not report.exists()
