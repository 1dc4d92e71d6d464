"""The README is the front door: short, names and links the paper, points only inside the clone,
and the licence and citation it names are there."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")


def test_the_readme_is_under_1500_words() -> None:
    assert len(README.split()) < 1500


def test_the_readme_names_and_links_the_paper() -> None:
    assert "ViSNeRF" in README and "https://arxiv.org/abs/2502.16731" in README


def test_the_readme_points_only_inside_the_clone() -> None:
    assert not re.search(r"\.\./shared|\]\(\.\./", README)


def test_the_licence_and_citation_are_there() -> None:
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    citation = (ROOT / "CITATION.cff").read_text()
    assert citation.startswith("cff-version: 1.2.0") and "2502.16731" in citation
    assert "## Glossary" in README
