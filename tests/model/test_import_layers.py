"""The model's subpackages import one way: representation <- rendering <- training / evaluation <-
commands, with no cycle between any two of them (lazy imports inside functions count too), and
the model never imports the server."""

import ast
import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[2] / "model" / "visnerf"


def imports_between_parts() -> dict[str, set[str]]:
    """For each top-level module or subpackage of ``visnerf``, the others it imports."""
    edges: dict[str, set[str]] = {}
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(PACKAGE).parts
        part = rel[0] if len(rel) > 1 else rel[0].removesuffix(".py")
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = [node.module] if isinstance(node, ast.ImportFrom) and node.module else (
                [a.name for a in node.names] if isinstance(node, ast.Import) else [])
            for name in names:
                if name.startswith("visnerf_server"):
                    edges.setdefault(part, set()).add("visnerf_server")
                elif name.startswith("visnerf.") and name.split(".")[1] != part:
                    edges.setdefault(part, set()).add(name.split(".")[1])
    return edges


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}

    def visit(node: str, path: list[str]) -> list[str] | None:
        state[node] = 1
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt):], nxt] if nxt in path else [*path, nxt]
            if state.get(nxt) is None and (cycle := visit(nxt, [*path, nxt])):
                return cycle
        state[node] = 2
        return None

    for start in sorted(edges):
        if state.get(start) is None and (cycle := visit(start, [start])):
            return cycle
    return None


def test_no_import_cycle_between_subpackages():
    edges = imports_between_parts()
    assert find_cycle(edges) is None, f"import cycle: {' -> '.join(find_cycle(edges) or [])}"


def test_the_layers_point_one_way():
    edges = imports_between_parts()
    assert not edges.get("representation", set()) - {"config", "runtime", "factor_codec"}
    assert "training" not in edges.get("rendering", set()) and "evaluation" not in edges.get("rendering", set())
    assert "rendering" not in edges.get("data", set()) and "training" not in edges.get("data", set())
    assert not any("commands" in targets for part, targets in edges.items() if part != "cli")


def test_the_model_never_imports_the_server():
    assert not [part for part, targets in imports_between_parts().items() if "visnerf_server" in targets]


def test_the_model_names_no_server_module_in_a_string():
    """``importlib.import_module("visnerf_server...")`` would bypass the import checks above: the
    server's sub-commands reach the CLI through an entry point (``cli.COMMAND_GROUP``)."""
    named = [f"{path.relative_to(PACKAGE)}: {node.value!r}" for path in PACKAGE.rglob("*.py")
             for node in ast.walk(ast.parse(path.read_text(), str(path)))
             if isinstance(node, ast.Constant) and isinstance(node.value, str)
             and re.match(r"^visnerf_server(\.|$)", node.value)]
    assert not named, named


def test_modules_named_in_docstrings_exist():
    """A docstring's pointer to a module (``visnerf.x.y``, ``rendering.x``) or a committed file
    (``bench/results/...``, ``docs/...``) names something that is in the tree."""
    root = PACKAGE.parents[1]
    missing = []
    for path in [*PACKAGE.rglob("*.py"), *(root / "server" / "visnerf_server").rglob("*.py")]:
        text = path.read_text()
        for name in re.findall(r"``(visnerf(?:_server)?(?:\.[a-z_0-9]+)+)``", text):
            parts = name.split(".")
            base = root / ("server" if parts[0] == "visnerf_server" else "model")
            # a module, a package, or a name inside one of them
            if not any((base.joinpath(*parts[:k]).with_suffix(".py")).exists() or (base.joinpath(*parts[:k]) / "__init__.py").exists()
                       for k in range(len(parts), 0, -1) if k >= 2):
                missing.append(f"{path.relative_to(root)}: {name}")
        for file in re.findall(r"(?<![\w/])((?:bench/results|docs)/[\w./-]+\.(?:md|json|png))", text):
            if not (root / file).exists():
                missing.append(f"{path.relative_to(root)}: {file}")
    assert not missing, missing


def test_the_cycle_finder_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None
