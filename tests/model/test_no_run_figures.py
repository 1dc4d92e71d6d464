"""The model's code states rules, not the history of runs: a figure in dB outside evaluation/ (where
scoring is the job) belongs in docs/decisions.md. A tolerance ("within 0.05 dB") is a rule."""

import re
from pathlib import Path

MODEL = Path(__file__).resolve().parents[2] / "model" / "visnerf"
FIGURE = re.compile(r"\d(?:\.\d+)?\s*dB\b")
TOLERANCE = re.compile(r"within\s+\d(?:\.\d+)?\s*dB\b")


def test_no_run_figures_in_the_model_code() -> None:
    found = []
    for path in sorted(MODEL.rglob("*.py")):
        if "evaluation" in path.relative_to(MODEL).parts:
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if FIGURE.search(TOLERANCE.sub("", line)):
                found.append(f"{path.relative_to(MODEL)}:{number}: {line.strip()}")
    assert not found, "run figures belong in docs/decisions.md:\n" + "\n".join(found)


def test_the_check_sees_a_figure() -> None:
    assert FIGURE.search(TOLERANCE.sub("", "scored 30.2 dB against 29.1"))
    assert not FIGURE.search(TOLERANCE.sub("", "frames within 0.05 dB of exhaustive ones"))
