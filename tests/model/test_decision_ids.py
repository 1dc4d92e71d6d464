"""Code names a decision by its id (``docs/decisions.md#<id>``); every id named exists, and the
register stays a register: one heading an id, at most 300 lines."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
REGISTER = ROOT / "docs" / "decisions.md"
TRIALS = ROOT / "docs" / "trials.md"
SOURCES = ("model", "server", "client", "bench", "scripts")
NAMED = re.compile(r"decisions\.md#([a-z0-9_]+\.[a-z0-9_]+)")
HEADING_PROSE = re.compile(r"decisions\.md,?\s*\(?\"")
TRIAL_ID = re.compile(r"\(`([a-z0-9_]+\.[a-z0-9_]+)`\)")
ENTRY = re.compile(r"^### ([a-z0-9_]+\.[a-z0-9_]+)$", re.MULTILINE)


def register_ids() -> list[str]:
    return ENTRY.findall(REGISTER.read_text())


def source_files() -> list[Path]:
    return [path for folder in SOURCES for path in sorted((ROOT / folder).rglob("*"))
            if path.suffix in (".py", ".js", ".html", ".md") and path.is_file()]


def test_every_id_named_in_code_exists() -> None:
    ids = set(register_ids())
    missing, prose = [], []
    for path in source_files():
        text = path.read_text()
        missing += [f"{path.relative_to(ROOT)}: {name}" for name in NAMED.findall(text) if name not in ids]
        prose += [str(path.relative_to(ROOT))] if HEADING_PROSE.search(text) else []
    assert not missing, "ids named but not in docs/decisions.md:\n" + "\n".join(missing)
    assert not prose, "name a decision by its id, not its heading:\n" + "\n".join(prose)


def test_every_id_the_trial_log_names_exists() -> None:
    ids = set(register_ids())
    named = TRIAL_ID.findall(TRIALS.read_text())
    assert named, "the trial log names the decisions its kept rows set"
    assert not sorted(set(named) - ids)


def test_the_register_is_short_and_each_id_is_once() -> None:
    ids = register_ids()
    assert len(REGISTER.read_text().splitlines()) <= 300
    assert len(ids) == len(set(ids)), sorted({i for i in ids if ids.count(i) > 1})


def test_the_checks_see_what_they_look_for() -> None:
    assert NAMED.findall("(docs/decisions.md#recipe.sparse_view_tv).") == ["recipe.sparse_view_tv"]
    assert HEADING_PROSE.search('(docs/decisions.md, "Rendering")')
    assert not HEADING_PROSE.search("docs/decisions.md#frames.chunks")
    assert ENTRY.findall("x\n### frames.chunks\nrule") == ["frames.chunks"]
