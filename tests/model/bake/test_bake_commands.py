"""``visnerf bake`` and ``visnerf render --bake``: files written, bad input refused with nothing written."""

from pathlib import Path

import numpy as np
from PIL import Image

from visnerf.bake.bake_file import read_bake
from visnerf.cli import main

CHECKPOINT = Path(__file__).resolve().parents[3] / "checkpoints" / "vortex_tf1.safetensors"


def test_bake_then_render_from_it(tmp_path, capsys) -> None:
    out = tmp_path / "v.bake"
    assert main(["bake", str(CHECKPOINT), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "bricks of 8^3" in printed and "colour: degree" in printed
    bake = read_bake(out)
    assert bake.header.shading == "sh" and bake.header.source["checkpoint"]
    png = tmp_path / "v.png"
    assert main(["render", str(CHECKPOINT), "--bake", str(out), "--size", "32x24", "-o", str(png)]) == 0
    image = np.asarray(Image.open(png))
    assert image.shape == (24, 32, 3) and image.std() > 0


def test_bad_input_writes_nothing(tmp_path, capsys) -> None:
    out = tmp_path / "v.bake"
    assert main(["bake", str(CHECKPOINT), "--param", "nope=1", "-o", str(out)]) == 2
    assert "unknown parameter" in capsys.readouterr().err
    assert main(["bake", str(CHECKPOINT), "--brick", "1", "-o", str(out)]) == 2
    assert "brick" in capsys.readouterr().err
    assert not out.exists()
    (tmp_path / "junk.bake").write_bytes(b"\x01" * 20)
    assert main(["render", str(CHECKPOINT), "--bake", str(tmp_path / "junk.bake"), "-o", str(tmp_path / "j.png")]) == 2
    assert "header length" in capsys.readouterr().err
    assert main(["render", str(CHECKPOINT), "--bake", str(out), "--param", "opacity_a=0.4",
                 "-o", str(tmp_path / "j.png")]) == 2
    assert not (tmp_path / "j.png").exists()


def test_info_states_the_bake_rules(capsys) -> None:
    import json

    assert main(["info", str(CHECKPOINT)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["bake"]["grid"] == doc["field"]["resolution"]
    assert "decisions.md#bake.grid" in doc["bake"]["grid_rule"] and "bake.shading" in doc["bake"]["colour"]
