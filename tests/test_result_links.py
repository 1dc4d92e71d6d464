"""Every relative link and picture in the README, the docs and the committed benchmark results names
a file that is in the tree: a report whose pictures were not committed reads as broken."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _documents() -> list[Path]:
    docs = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), *sorted((ROOT / "bench" / "results").rglob("*.md"))]
    return [d for d in docs if d.is_file()]


def _relative_targets(document: Path) -> list[str]:
    targets = []
    for target in LINK.findall(document.read_text(encoding="utf-8")):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL or an anchor in the same page
        targets.append(target.split("#", 1)[0])
    return [t for t in targets if t]


@pytest.mark.parametrize("document", _documents(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_name_files_in_the_tree(document: Path) -> None:
    missing = [t for t in _relative_targets(document) if not (document.parent / t).exists()]
    assert not missing, f"{document.relative_to(ROOT)} links to files that are not there: {missing}"
