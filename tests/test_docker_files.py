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


# --- replicas behind nginx: docker/nginx.conf and docker/compose.yaml ----------------------------

NGINX_CONF = REPO / "docker" / "nginx.conf"
COMPOSE_FILE = REPO / "docker" / "compose.yaml"
NGINX_SIZE_UNITS = {"": 1, "k": 1024, "m": 1024**2, "g": 1024**3}
NGINX_TIME_UNITS = {"ms": 0.001, "s": 1, "m": 60, "h": 3600}


@dataclass
class NginxDirective:
    name: str
    args: list[str]
    block: list["NginxDirective"] | None = None


def parse_nginx(text: str) -> list[NginxDirective]:
    """nginx's configuration syntax: directives with arguments, ending in ``;`` or a ``{ block }``."""
    tokens = re.findall(r'"[^"]*"|[{};]|[^\s{};"]+', re.sub(r"#[^\n]*", "", text))
    stack: list[list[NginxDirective]] = [[]]
    words: list[str] = []
    for token in tokens:
        if token == ";":
            stack[-1].append(NginxDirective(words[0], words[1:]))
            words = []
        elif token == "{":
            directive = NginxDirective(words[0], words[1:], [])
            stack[-1].append(directive)
            stack.append(directive.block)  # type: ignore[arg-type]
            words = []
        elif token == "}":
            assert not words, f"directive without ';' before '}}': {words}"
            stack.pop()
        else:
            words.append(token.strip('"'))
    assert len(stack) == 1 and not words, "unbalanced braces in nginx.conf"
    return stack[0]


def directives(block: list[NginxDirective], name: str) -> list[NginxDirective]:
    return [d for d in block if d.name == name]


def only(block: list[NginxDirective], name: str) -> NginxDirective:
    (directive,) = directives(block, name)
    return directive


def nginx_size(value: str) -> int:
    number, unit = re.fullmatch(r"(\d+)([kmg]?)", value.lower()).groups()  # type: ignore[union-attr]
    return int(number) * NGINX_SIZE_UNITS[unit]


def nginx_seconds(value: str) -> float:
    number, unit = re.fullmatch(r"(\d+)(ms|s|m|h)?", value).groups()  # type: ignore[union-attr]
    return int(number) * NGINX_TIME_UNITS[unit or "s"]


def nginx_http() -> list[NginxDirective]:
    return only(parse_nginx(NGINX_CONF.read_text()), "http").block  # type: ignore[return-value]


def nginx_server() -> list[NginxDirective]:
    return only(nginx_http(), "server").block  # type: ignore[return-value]


def location(path: str) -> NginxDirective:
    """The location nginx picks for ``path``: the first regular expression that matches, else ``/``."""
    locations = directives(nginx_server(), "location")
    for loc in locations:
        if loc.args[0] == "~" and re.search(loc.args[1], path):
            return loc
    return next(loc for loc in locations if loc.args == ["/"])


def upstream(name: str) -> list[NginxDirective]:
    (block,) = [d.block for d in directives(nginx_http(), "upstream") if d.args == [name]]
    return block or []


def proxied_to(loc: NginxDirective) -> str:
    """The upstream a location passes its requests to."""
    (target,) = only(loc.block or [], "proxy_pass").args
    return target.removeprefix("http://")


def server_defaults() -> dict:
    from visnerf_server.settings import Settings

    return {name: f.default for name, f in Settings.model_fields.items()}


def test_nginx_takes_uploads_as_large_as_the_server_does() -> None:
    (size,) = only(nginx_server(), "client_max_body_size").args
    assert nginx_size(size) == server_defaults()["max_upload_bytes"]


def test_nginx_waits_for_the_servers_own_render_timeout() -> None:
    server = nginx_server()
    timeout = server_defaults()["render_timeout_s"]
    for name in ("proxy_read_timeout", "proxy_send_timeout", "proxy_next_upstream_timeout"):
        seconds = nginx_seconds(only(server, name).args[0])
        assert timeout < seconds <= timeout + 30, f"{name} {seconds} s: the server's own 503/504 comes at {timeout} s"
    assert nginx_seconds(only(server, "proxy_connect_timeout").args[0]) <= 5  # a stopped replica: next one, fast


def test_nginx_balances_every_replica_round_robin_with_passive_checks() -> None:
    rest = proxied_to(location("/api/scenes"))
    servers = directives(upstream(rest), "server")
    assert len(servers) >= 2
    for server in servers:
        assert server.args[0].endswith(":8000"), server.args  # the image's EXPOSE
        options = {a.partition("=")[0] for a in server.args[1:]}
        assert {"max_fails", "fail_timeout"} <= options, server.args
    methods = {"least_conn", "ip_hash", "hash", "random"}
    assert not [d.name for d in upstream(rest) if d.name in methods]
    assert directives(upstream(rest), "zone")  # shared by the worker processes
    for path in ("/api/scenes/nyx", "/api/scenes/nyx/render", "/api/scenes/nyx/stream", "/api/ready", "/"):
        assert proxied_to(location(path)) == rest, path


def test_nginx_sends_movie_jobs_to_one_replica_at_a_time() -> None:
    from visnerf_server.routers.movies import router

    paths = {r.path.replace("{scene_id}", "nyx").replace("{job_id}", "j1") for r in router.routes}
    assert len(paths) == 3
    movies = {proxied_to(location(path)) for path in paths}
    assert len(movies) == 1, "a job's status and file live on the replica that took it"
    servers = directives(upstream(movies.pop()), "server")
    assert sum("backup" not in s.args for s in servers) == 1
    rest = {s.args[0] for s in directives(upstream(proxied_to(location("/api/scenes"))), "server")}
    assert {s.args[0] for s in servers} == rest


def test_nginx_retries_refused_and_overloaded_requests_on_another_replica() -> None:
    retry = set(only(nginx_server(), "proxy_next_upstream").args)
    assert {"error", "timeout", "http_502", "http_503"} <= retry
    assert "non_idempotent" not in retry  # a movie job's POST must not be sent twice
    assert int(only(nginx_server(), "proxy_next_upstream_tries").args[0]) >= 2
    render = location("/api/scenes/nyx/render")
    assert "non_idempotent" in only(render.block, "proxy_next_upstream").args  # type: ignore[arg-type]
    movies = location("/api/scenes/nyx/movies").block or []
    assert not directives(movies, "proxy_next_upstream")  # the server's: no POST sent twice


def test_nginx_passes_the_client_and_the_websocket_upgrade() -> None:
    from visnerf_server.routers.stream import router

    headers = {d.args[0].lower(): d.args[1] for d in directives(nginx_server(), "proxy_set_header")}
    assert headers["x-forwarded-for"] == "$proxy_add_x_forwarded_for"
    assert headers["x-forwarded-proto"] == "$scheme"
    assert headers["upgrade"] == "$http_upgrade"
    maps = {d.args[1]: {e.name: e.args[0] for e in d.block or []} for d in directives(nginx_http(), "map")}
    # Host keeps the port: the stream's Origin check compares it with the page's origin.
    assert maps[headers["host"]]["default"] == "$http_host"
    assert maps[headers["connection"]] == {"default": "upgrade", "": ""}  # keep-alive unless upgrading
    assert only(nginx_server(), "proxy_http_version").args == ["1.1"]
    # A location with its own proxy_set_header would inherit none of the server's.
    locations = directives(nginx_server(), "location")
    assert not [loc.args for loc in locations if directives(loc.block or [], "proxy_set_header")]
    (stream_path,) = [r.path for r in router.routes]
    stream = location(stream_path.replace("{scene_id}", "nyx"))
    assert stream.args[0] == "~"
    assert nginx_seconds(only(stream.block, "proxy_read_timeout").args[0]) >= 600  # type: ignore[arg-type]


def compose() -> dict:
    yaml = pytest.importorskip("yaml")
    return yaml.safe_load(COMPOSE_FILE.read_text())


def replicas(spec: dict) -> dict[str, dict]:
    return {name: s for name, s in spec["services"].items() if "build" in s}


def test_compose_runs_two_replicas_of_the_server_image_on_one_store() -> None:
    spec = compose()
    servers = replicas(spec)
    assert len(servers) >= 2
    env = " ".join(arguments(SERVER_IMAGE, "ENV"))
    checkpoints = re.search(r"VISNERF_CHECKPOINTS_DIR=(\S+)", env).group(1)  # type: ignore[union-attr]
    stores = set()
    for service in servers.values():
        build = service["build"]
        assert (COMPOSE_FILE.parent / build["context"] / build["dockerfile"]).resolve() == SERVER_IMAGE
        mounts = [v.split(":") for v in service["volumes"]]
        stores |= {source for source, target, *_ in mounts if target == checkpoints}
    assert len(stores) == 1 and stores <= set(spec["volumes"]), "every replica must mount the same store"
    for name in {d.args[0] for d in directives(nginx_http(), "upstream")}:
        assert {d.args[0].rsplit(":", 1)[0] for d in directives(upstream(name), "server")} == set(servers)


def test_compose_settings_are_valid_and_trust_only_nginx() -> None:
    from visnerf_server.settings import Settings

    spec = compose()
    nginx = spec["services"]["nginx"]
    proxy_address = nginx["networks"]["visnerf"]["ipv4_address"]
    for service in replicas(spec).values():
        env = service["environment"]
        assert env["VISNERF_TRUSTED_PROXIES"] == proxy_address
        assert service["networks"]["visnerf"]["ipv4_address"] != proxy_address
        values = {k.removeprefix("VISNERF_").lower(): v for k, v in env.items() if k.startswith("VISNERF_")}
        settings = Settings(**values)  # every value parses
        assert 0 < settings.store_poll_s <= 10
        assert env["VISNERF_TOKEN_FILE"] == f"/run/secrets/{service['secrets'][0]}"  # one token for all
    assert set(nginx["depends_on"]) == set(replicas(spec))
    # Started once the image's HEALTHCHECK (/api/ready) passes on every replica.
    assert all(d["condition"] == "service_healthy" for d in nginx["depends_on"].values())


def test_compose_pins_nginx_and_publishes_on_loopback() -> None:
    nginx = compose()["services"]["nginx"]
    tag = nginx["image"].partition(":")[2]
    assert re.match(r"\d+\.\d+\.\d+", tag), f"{nginx['image']}: pin a full version"
    assert [p for p in nginx["ports"] if p.startswith("127.0.0.1:")] == nginx["ports"]
    listen = only(nginx_server(), "listen").args[0]
    assert all(p.rsplit(":", 1)[1] == listen for p in nginx["ports"])
    assert f"./{NGINX_CONF.name}:/etc/nginx/nginx.conf:ro" in nginx["volumes"]
    assert is_excluded("docker/visnerf_token", read_dockerignore())  # the token secret stays out of builds


def test_nginx_sends_each_bake_to_one_replica_and_keeps_it() -> None:
    bake = location("/api/scenes/nyx/bake")
    assert bake.args[0] == "~"
    servers = directives(upstream(proxied_to(bake)), "server")
    rest = {s.args[0] for s in directives(upstream(proxied_to(location("/api/scenes"))), "server")}
    assert {s.args[0] for s in servers} == rest
    assert only(upstream(proxied_to(bake)), "hash").args == ["$request_uri", "consistent"]
    retry = only(bake.block, "proxy_next_upstream").args  # type: ignore[arg-type]
    assert "http_503" not in retry, "a bake being built is asked for again by the client, on its replica"
    assert only(bake.block, "proxy_cache").args == ["bakes"]  # type: ignore[arg-type]
    zones = [d.args for d in directives(nginx_http(), "proxy_cache_path")]
    assert any("keys_zone=bakes:8m" in args for args in zones)
