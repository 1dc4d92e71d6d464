"""The code states rules, not the history of runs: a figure in dB, ms, MB or GB, or a CPU's name,
in model/ (outside evaluation/, where scoring is the job) or server/ belongs in
docs/decisions.md, under an id the code names. A tolerance ("within 0.05 dB") is a rule."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = (ROOT / "model" / "visnerf", ROOT / "server" / "visnerf_server")
FIGURE = re.compile(r"\d(?:\.\d+)?\s*(?:dB|ms|MB|GB)\b|\b(?:EPYC|Xeon|Zen \d)\b")
TOLERANCE = re.compile(r"within\s+\d(?:\.\d+)?\s*dB\b")


def test_no_run_figures_in_the_code() -> None:
    found = []
    for package in PACKAGES:
        for path in sorted(package.rglob("*.py")):
            if "evaluation" in path.relative_to(package).parts:
                continue
            for number, line in enumerate(path.read_text().splitlines(), 1):
                if FIGURE.search(TOLERANCE.sub("", line)):
                    found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
    assert not found, "run figures belong in docs/decisions.md:\n" + "\n".join(found)


def test_the_check_sees_a_figure() -> None:
    for text in ("scored 30.2 dB against 29.1", "a step 41.3 ms", "peak 1653 MB", "2.8 GB resident",
                 "on an AMD EPYC", "a Xeon with AMX", "a Zen 5 core"):
        assert FIGURE.search(TOLERANCE.sub("", text)), text
    assert not FIGURE.search(TOLERANCE.sub("", "frames within 0.05 dB of exhaustive ones"))
    assert not FIGURE.search("1 << 20 bytes, MAX_MB = 8")
