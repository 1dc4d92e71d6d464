"""Static checks of the container files, for machines without a Docker engine: docker/Dockerfile.server,
docker/Dockerfile.train and .dockerignore, and the dependency split the server image relies on (the
server imports nothing from the ``train`` extra, found by reading the sources, not by importing them)."""

import ast
import json
import posixpath
import re
import shlex
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from visnerf.cli import _COMMAND_MODULES

tomllib = pytest.importorskip("tomllib")  # Python 3.11+

REPO = Path(__file__).resolve().parents[1]
SERVER_IMAGE = REPO / "docker" / "Dockerfile.server"
TRAIN_IMAGE = REPO / "docker" / "Dockerfile.train"
IMAGES = [SERVER_IMAGE, TRAIN_IMAGE]
SOURCE_ROOTS = {"visnerf": REPO / "model" / "visnerf", "visnerf_server": REPO / "server" / "visnerf_server"}
IMPORT_NAMES = {"scikit-image": "skimage", "pillow": "PIL", "pyyaml": "yaml"}
"""Distribution name (lower case) to import name, where the two differ."""
THREAD_VARIABLES = ("VISNERF_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


# --- reading a Dockerfile ----------------------------------------------------------------------


@dataclass(frozen=True)
class Instruction:
    keyword: str
    args: str


def parse_dockerfile(text: str) -> list[Instruction]:
    """The instructions in order, comments and blank lines dropped, continuation lines joined."""
    instructions: list[Instruction] = []
    pending = ""
    for line in text.splitlines():
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        if stripped.endswith("\\"):
            pending += stripped[:-1] + " "
            continue
        keyword, _, args = (pending + stripped).partition(" ")
        instructions.append(Instruction(keyword.upper(), args.strip()))
        pending = ""
    assert not pending, "the Dockerfile ends inside a continued line"
    return instructions


def arguments(path: Path, keyword: str) -> list[str]:
    return [i.args for i in parse_dockerfile(path.read_text()) if i.keyword == keyword]


def without_flags(args: str) -> list[str]:
    """The words of a shell-form instruction, ``--flag=value`` options dropped."""
    words = json.loads(args) if args.startswith("[") else shlex.split(args)
    return [w for w in words if not w.startswith("--")]


def copy_sources(path: Path) -> list[str]:
    """Every source of the image's COPY and ADD instructions from the build context."""
    sources: list[str] = []
    for keyword in ("COPY", "ADD"):
        for args in arguments(path, keyword):
            if "--from=" not in args:
                sources += without_flags(args)[:-1]
    return sources


def pip_installs(path: Path) -> list[str]:
    """Each ``pip install ...`` command of the image's RUN instructions."""
    commands = []
    for args in arguments(path, "RUN"):
        commands += [part.strip() for part in re.split(r"&&|;", args) if "pip install" in part]
    return commands


# --- .dockerignore, with Docker's matching rules ------------------------------------------------


def glob_to_regex(pattern: str) -> re.Pattern[str]:
    """A .dockerignore pattern (Go's filepath.Match syntax plus ``**``) as a regular expression."""
    out, i = [], 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out.append("(?:.*/)?")
            i += 3
        elif pattern.startswith("**", i):
            out.append(".*")
            i += 2
        elif pattern[i] == "*":
            out.append("[^/]*")
            i += 1
        elif pattern[i] == "?":
            out.append("[^/]")
            i += 1
        elif pattern[i] == "[":
            end = pattern.index("]", i + 1)
            members = pattern[i + 1 : end]
            out.append("[" + ("^" + members[1:] if members[:1] in ("!", "^") else members) + "]")
            i = end + 1
        else:
            out.append(re.escape(pattern[i]))
            i += 1
    return re.compile("".join(out) + r"\Z")


@dataclass(frozen=True)
class IgnoreRule:
    regex: re.Pattern[str]
    keeps: bool
    """A ``!pattern``: puts back what earlier patterns left out."""


def read_dockerignore(path: Path = REPO / ".dockerignore") -> list[IgnoreRule]:
    rules = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        keeps = line.startswith("!")
        pattern = posixpath.normpath(line.removeprefix("!").strip()).lstrip("/")
        rules.append(IgnoreRule(glob_to_regex(pattern), keeps))
    return rules


def is_excluded(relative: str, rules: list[IgnoreRule]) -> bool:
    """Docker's rule: the last pattern that matches the path, or a folder above it, decides."""
    parts = relative.strip("/").split("/")
    candidates = ["/".join(parts[:n]) for n in range(1, len(parts) + 1)]
    excluded = False
    for rule in rules:
        if any(rule.regex.match(c) for c in candidates):
            excluded = not rule.keeps
    return excluded


# --- the modules `visnerf serve` loads, read statically --------------------------------------------


def module_file(module: str) -> Path | None:
    """The source file of one of the project's modules; None for the standard library and third parties."""
    top, *rest = module.split(".")
    if top not in SOURCE_ROOTS:
        return None
    base = SOURCE_ROOTS[top].joinpath(*rest)
    for candidate in (base / "__init__.py", base.with_suffix(".py")):
        if candidate.is_file():
            return candidate
    return None


def _is_type_checking(test: ast.expr) -> bool:
    return "TYPE_CHECKING" in ast.unparse(test)


def imported_names(path: Path, module_level_only: bool) -> Iterator[str]:
    """Modules a file imports: those its import runs, or (``module_level_only=False``) also those its
    functions import when called. Imports under ``if TYPE_CHECKING:`` never run and are skipped."""
    stack: list[ast.AST] = [ast.parse(path.read_text(), str(path))]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            yield node.module
            yield from (f"{node.module}.{alias.name}" for alias in node.names)
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child.test):
                stack.extend(child.orelse)
            elif not (module_level_only and isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)):
                stack.append(child)


def third_party_imports(starts: Iterable[str], module_level_only: bool) -> dict[str, str]:
    """Top-level names of the packages outside the project reachable from ``starts``, each with the
    project module that imports it."""
    seen: set[str] = set()
    found: dict[str, str] = {}
    todo = list(starts)
    while todo:
        module = todo.pop()
        path = module_file(module)
        if path is None or module in seen:
            continue
        seen.add(module)
        parts = module.split(".")
        todo += [".".join(parts[:n]) for n in range(1, len(parts))]  # importing a module runs its packages
        for name in imported_names(path, module_level_only):
            top = name.split(".")[0]
            if top in SOURCE_ROOTS:
                todo.append(name)
            else:
                found.setdefault(top, module)
    return found


def server_modules() -> list[str]:
    root = SOURCE_ROOTS["visnerf_server"]
    return ["visnerf_server." + ".".join(p.relative_to(root).with_suffix("").parts) for p in root.rglob("*.py")]


def serve_imports() -> dict[str, str]:
    """What ``visnerf serve`` can import: the command line's modules as it builds its parser (their
    module-level imports), and anything any server module imports, whenever it runs."""
    cli = third_party_imports(["visnerf.cli", *_COMMAND_MODULES], module_level_only=True)
    return {**cli, **third_party_imports(server_modules(), module_level_only=False)}


def pyproject() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def distribution(requirement: str) -> str:
    """The distribution a requirement names, lower case, without extras or versions."""
    return re.split(r"[\[<>=!~;\s]", requirement.strip(), maxsplit=1)[0].lower()


def train_only() -> set[str]:
    return {distribution(r) for r in pyproject()["project"]["optional-dependencies"]["train"]}


# --- the tests ---------------------------------------------------------------------------------


@pytest.mark.parametrize("image", IMAGES, ids=lambda p: p.name)
def test_the_base_image_is_pinned_to_a_full_version(image: Path) -> None:
    (base,) = [without_flags(args)[0] for args in arguments(image, "FROM")]
    tag = base.partition("@")[0].partition(":")[2]
    assert "@sha256:" in base or re.match(r"\d+\.\d+\.\d+", tag), f"{base}: pin a full version or a digest"
    assert tag != "latest"


@pytest.mark.parametrize("image", IMAGES, ids=lambda p: p.name)
def test_the_image_runs_as_a_user_that_is_not_root(image: Path) -> None:
    users = arguments(image, "USER")
    assert users, "no USER: the container would run as root"
    assert users[-1].split(":")[0] not in ("root", "0")


@pytest.mark.parametrize("image", IMAGES, ids=lambda p: p.name)
def test_the_command_is_in_exec_form(image: Path) -> None:
    commands = arguments(image, "CMD") + arguments(image, "ENTRYPOINT")
    assert commands
    for args in commands:
        words = json.loads(args)  # shell form is not JSON: /bin/sh would be PID 1 and swallow SIGTERM
        assert isinstance(words, list) and all(isinstance(w, str) for w in words)


def test_the_server_image_serves_and_checks_its_health() -> None:
    (command,) = arguments(SERVER_IMAGE, "CMD")
    assert json.loads(command)[:2] == ["visnerf", "serve"]
    (health,) = arguments(SERVER_IMAGE, "HEALTHCHECK")
    assert "CMD" in health and "/api/ready" in health


@pytest.mark.parametrize("image", IMAGES, ids=lambda p: p.name)
def test_every_copy_source_exists_and_is_in_the_build_context(image: Path) -> None:
    rules = read_dockerignore()
    sources = copy_sources(image)
    assert {"pyproject.toml", "README.md", "model", "server"} <= set(sources)
    for source in sources:
        assert (REPO / source).exists(), f"COPY {source}: not in the repository"
        assert not is_excluded(source, rules), f"COPY {source}: left out by .dockerignore"


def test_the_files_the_server_image_needs_are_in_the_build_context() -> None:
    rules = read_dockerignore()
    needed = [p for root in ("model", "server", "client") for p in (REPO / root).rglob("*") if p.is_file()]
    needed = [p for p in needed if "__pycache__" not in p.parts]
    needed += list((REPO / "checkpoints").glob("*.safetensors"))
    assert len(list((REPO / "checkpoints").glob("*.safetensors"))) >= 1
    left_out = [str(p.relative_to(REPO)) for p in needed if is_excluded(str(p.relative_to(REPO)), rules)]
    assert not left_out


@pytest.mark.parametrize(
    "path",
    [
        ".git/HEAD",
        ".venv/bin/python",
        "runs/tangle.safetensors",
        "runs/tangle.log.csv",
        "data/nyx/transforms_train.json",
        "bench/results/server_load.json",
        "tests/_artifacts/client.png",
        "model/visnerf/__pycache__/cli.cpython-311.pyc",
        ".pytest_cache/v/cache/nodeids",
        ".ruff_cache/content",
        ".hypothesis/constants/a3a0",
        "visnerf.egg-info/PKG-INFO",
        "tangle.safetensors",
        "tests/server/model.safetensors",
        "runs/tangle.resume",
        "checkpoints/.upload-1a2b.safetensors",
    ],
)
def test_the_dockerignore_leaves_out(path: str) -> None:
    assert is_excluded(path, read_dockerignore())


@pytest.mark.parametrize(
    "path",
    ["pyproject.toml", "README.md", "model/visnerf/cli.py", "server/visnerf_server/app.py", "client/index.html",
     "checkpoints/plume_time.safetensors", "checkpoints/plume_time.log.json"],
)
def test_the_dockerignore_keeps(path: str) -> None:
    assert not is_excluded(path, read_dockerignore())


def test_the_matcher_follows_dockers_rules() -> None:
    rules = [IgnoreRule(glob_to_regex(p.removeprefix("!")), p.startswith("!"))
             for p in ("**/*.bin", "!keep/*.bin", "cache", "a?c", "[xy].txt")]
    assert is_excluded("deep/er/f.bin", rules) and is_excluded("f.bin", rules)
    assert not is_excluded("keep/f.bin", rules) and is_excluded("keep/sub/f.bin", rules)
    assert is_excluded("cache/x/y", rules) and not is_excluded("src/cache", rules)
    assert is_excluded("abc", rules) and not is_excluded("a/c", rules)
    assert is_excluded("x.txt", rules) and not is_excluded("z.txt", rules)


def test_the_server_image_installs_the_server_extra_and_nothing_for_training() -> None:
    installs = pip_installs(SERVER_IMAGE)
    assert any(re.search(r"""pip install ["']?\.\[server\]["']?$""", c) for c in installs), installs
    for command in installs:
        words = {distribution(w) for w in shlex.split(command)[2:] if not w.startswith("-")}
        assert not words & train_only(), command
        assert "[train" not in command and "[test" not in command, command


def test_the_train_image_installs_the_train_extra() -> None:
    assert any(re.search(r"""pip install ["']?\.\[train\]["']?$""", c) for c in pip_installs(TRAIN_IMAGE))


def test_the_extras_keep_training_packages_out_of_the_server_install() -> None:
    project = pyproject()["project"]
    extras = project["optional-dependencies"]
    served = {distribution(r) for r in project["dependencies"] + extras["server"]}
    assert {"scikit-image", "matplotlib"} <= train_only()
    assert not served & train_only()
    assert "visnerf[train]" in extras["test"]  # the tests need everything


def test_visnerf_serve_imports_nothing_from_the_train_extra() -> None:
    imports = serve_imports()
    assert {"fastapi", "uvicorn", "torch", "safetensors"} <= set(imports)  # the reading finds the server's
    train_modules = {IMPORT_NAMES.get(d, d.replace("-", "_")) for d in train_only()}
    assert not {name: imports[name] for name in train_modules if name in imports}


def test_the_import_reading_sees_imports_inside_functions() -> None:
    # Training validation imports scikit-image when it first computes SSIM, not at module level.
    assert "skimage" in third_party_imports(["visnerf.training.trainer"], module_level_only=False)
    assert "skimage" not in third_party_imports(["visnerf.training.trainer"], module_level_only=True)


@pytest.mark.parametrize("image", IMAGES, ids=lambda p: p.name)
def test_the_image_leaves_the_thread_count_to_the_cpu_quota(image: Path) -> None:
    settings = " ".join(arguments(image, "ENV") + arguments(image, "ARG") + arguments(image, "RUN"))
    assert not [name for name in THREAD_VARIABLES if name in settings]


def test_the_server_state_folder_is_a_volume() -> None:
    volumes = [v for args in arguments(SERVER_IMAGE, "VOLUME") for v in without_flags(args)]
    assert "/app/state" in volumes
    assert "VISNERF_STATE_DIR=/app/state" in " ".join(arguments(SERVER_IMAGE, "ENV"))
