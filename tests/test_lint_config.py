"""Lint claims only what it checks: every ``noqa`` names a rule ruff is told to select."""

import re
import subprocess
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]
NOQA = re.compile(r"#\s*noqa:\s*([A-Z]+[0-9]+(?:\s*,\s*[A-Z]+[0-9]+)*)")


def selected_prefixes() -> tuple[str, ...]:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return tuple(config["tool"]["ruff"]["lint"]["select"])


def test_every_noqa_names_a_selected_rule() -> None:
    prefixes = selected_prefixes()
    files = subprocess.run(["git", "ls-files", "*.py"], cwd=ROOT, capture_output=True, text=True,
                           check=True).stdout.split()
    dead = []
    for name in files:
        for number, line in enumerate((ROOT / name).read_text().splitlines(), 1):
            for group in NOQA.findall(line):
                dead += [f"{name}:{number}: {code}" for code in re.split(r"\s*,\s*", group)
                         if re.match(r"[A-Z]+", code).group(0) not in prefixes]
    assert not dead, "noqa for rules ruff does not select:\n" + "\n".join(dead)
