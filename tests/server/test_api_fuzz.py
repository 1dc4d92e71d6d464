"""Fuzzing of the HTTP API from its own OpenAPI schema (schemathesis), against a real ``visnerf serve``
on copies of the bundled checkpoints: no generated request, valid or not, gets a 5xx answer, and an
upload or a scene delete without the token, or with a wrong one, is refused (401, 403) and changes nothing;
an upload with the token whose body is not a checkpoint is refused with a 4xx.

Each operation gets MAX_EXAMPLES requests, drawn from the schema (positive) and from outside it
(negative), derandomized so that a run repeats, without shrinking. Scene ids are random or, as often,
a bundled scene's; the GET render route also gets scene parameters (its schema cannot list them). A
5xx fails with the request (a curl command) and the server's log since it (the traceback).
"""

import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
import requests
import schemathesis
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from schemathesis import Case, GenerationMode
from server_helpers import TOKEN, LiveServer, serve_process

BUNDLED = Path(__file__).resolve().parents[2] / "checkpoints"
MAX_EXAMPLES = 30
MAX_IMAGE_SIZE = 64
"""The fuzzed server's largest frame side, so that every render the fuzzer asks for is cheap."""
REQUEST_TIMEOUT_S = 60.0
OPERATIONS = [
    ("GET", "/api/health"),
    ("GET", "/api/ready"),
    ("GET", "/api/limits"),
    ("GET", "/api/scenes"),
    ("GET", "/api/scenes/{scene_id}"),
    ("GET", "/api/scenes/{scene_id}/render"),
    ("POST", "/api/scenes/{scene_id}/render"),
    ("GET", "/api/scenes/{scene_id}/bake"),
    ("PUT", "/api/scenes/{scene_id}"),
    ("DELETE", "/api/scenes/{scene_id}"),
    ("POST", "/api/scenes/{scene_id}/movies"),
    ("GET", "/api/movies/{job_id}"),
    ("GET", "/api/movies/{job_id}/file"),
    ("DELETE", "/api/movies/{job_id}"),
]
RENDER_GET = ("GET", "/api/scenes/{scene_id}/render")
BAKE_GET = ("GET", "/api/scenes/{scene_id}/bake")
BY_NAME = {RENDER_GET, BAKE_GET}
"""Scene parameters go in their queries by their own names, which their schemas cannot list."""
GUARDED = {("PUT", "/api/scenes/{scene_id}"), ("DELETE", "/api/scenes/{scene_id}")}
"""Operations that need the token (a movie job's id is its own key: cancelling one needs no token)."""
AS_GENERATED = "as generated"
FUZZ = settings(
    max_examples=MAX_EXAMPLES,
    derandomize=True,
    database=None,
    deadline=None,
    phases=[Phase.explicit, Phase.generate],
    suppress_health_check=list(HealthCheck),
)


@dataclass
class FuzzTarget:
    server: LiveServer
    schema: schemathesis.BaseSchema
    openapi: dict[str, Any]
    scenes: dict[str, list[str]]
    """Scene id to its parameter names."""


@pytest.fixture(scope="module")
def target(tmp_path_factory: pytest.TempPathFactory) -> Iterator[FuzzTarget]:
    work = tmp_path_factory.mktemp("fuzz")
    ckpt_dir = work / "checkpoints"
    ckpt_dir.mkdir()
    for checkpoint in sorted(BUNDLED.glob("*.safetensors")):
        shutil.copy(checkpoint, ckpt_dir / checkpoint.name)
    env = {"VISNERF_MAX_IMAGE_SIZE": str(MAX_IMAGE_SIZE)}
    with serve_process(ckpt_dir, work, env, ready_timeout_s=120) as server:
        listing = httpx.get(f"{server.url}/api/scenes").json()
        scenes = {s["id"]: [axis["name"] for axis in s["params"]] for s in listing}
        openapi = httpx.get(f"{server.url}/openapi.json").json()
        schema = schemathesis.openapi.from_url(f"{server.url}/openapi.json")
        yield FuzzTarget(server, schema, openapi, scenes)


# --- generating requests -----------------------------------------------------------------------


def inputs(target: FuzzTarget, method: str, path: str, beyond_the_path: bool = False) -> bool:
    """Whether the operation takes any input (or, ``beyond_the_path``, any but its path)."""
    operation = target.openapi["paths"][path][method.lower()]
    parameters = [p for p in operation.get("parameters", []) if not (beyond_the_path and p["in"] == "path")]
    return bool(parameters or operation.get("requestBody"))


def with_scene_parameters(cases: st.SearchStrategy[Case], names: list[str]) -> st.SearchStrategy[Case]:
    """Adds up to three scene parameters (or an unknown name) with any text, numbers or not."""
    values = st.one_of(st.floats().map(repr), st.text(max_size=12))
    extra = st.dictionaries(st.sampled_from([*names, "not_a_parameter"]), values, max_size=3)

    def add(case: Case, query: dict[str, str]) -> Case:
        case.query = {**(case.query or {}), **query}
        return case

    return st.builds(add, cases, extra)


def cases(target: FuzzTarget, method: str, path: str) -> st.SearchStrategy[Case]:
    operation = target.schema[path][method]
    negative = [GenerationMode.NEGATIVE] if inputs(target, method, path) else []
    strategies = [operation.as_strategy(generation_mode=mode) for mode in [GenerationMode.POSITIVE, *negative]]
    if "{scene_id}" in path:
        negative = [GenerationMode.NEGATIVE] if inputs(target, method, path, beyond_the_path=True) else []
        for scene_id, names in target.scenes.items():
            for mode in [GenerationMode.POSITIVE, *negative]:
                fixed = operation.as_strategy(generation_mode=mode, path_parameters={"scene_id": scene_id})
                strategies.append(with_scene_parameters(fixed, names) if (method, path) in BY_NAME else fixed)
    return st.one_of(strategies)


# --- sending them ------------------------------------------------------------------------------


def send(server: LiveServer, case: Case, authorization: str | None = AS_GENERATED) -> requests.Response:
    """The request ``case`` describes; ``authorization`` replaces its Authorization header (None: none)."""
    request = case.as_transport_kwargs(base_url=server.url)
    if authorization != AS_GENERATED:
        headers = {k: v for k, v in request["headers"].items() if k.lower() != "authorization"}
        request["headers"] = headers if authorization is None else {**headers, "Authorization": authorization}
    return requests.request(**request, timeout=REQUEST_TIMEOUT_S)


def report(server: LiveServer, case: Case, response: requests.Response, log_offset: int) -> str:
    """The request to reproduce, the answer, and what the server logged since the request was sent."""
    log = server.log_path.read_bytes()[log_offset:].decode(errors="replace")
    return (
        f"{case.method} {case.formatted_path} answered {response.status_code}\n"
        f"reproduce with: {case.as_curl_command(base_url=server.url)}\n"
        f"answer: {response.text[:1000]}\n"
        f"server log since the request:\n{log[-6000:]}"
    )


def check_answer(server: LiveServer, case: Case, authorization: str | None, allowed: set[int] | None) -> None:
    offset = server.log_path.stat().st_size
    response = send(server, case, authorization)
    building = (case.method, case.path) == BAKE_GET and response.status_code == 503 and "retry-after" in response.headers
    assert response.status_code < 500 or building, report(server, case, response, offset)
    if allowed is not None:
        assert response.status_code in allowed, report(server, case, response, offset)


def scene_ids(server: LiveServer) -> list[str]:
    return sorted(s["id"] for s in httpx.get(f"{server.url}/api/scenes").json())


# --- the tests ---------------------------------------------------------------------------------


@pytest.mark.slow
def test_every_operation_of_the_schema_is_fuzzed(target: FuzzTarget) -> None:
    listed = {(method.upper(), path) for path, item in target.openapi["paths"].items() for method in item}
    assert listed == set(OPERATIONS)
    assert sorted(target.scenes) == sorted(p.stem for p in BUNDLED.glob("*.safetensors"))


@pytest.mark.slow
@pytest.mark.parametrize(("method", "path"), OPERATIONS, ids=[f"{m} {p}" for m, p in OPERATIONS])
def test_no_generated_request_gets_a_server_error(target: FuzzTarget, method: str, path: str) -> None:
    server = target.server
    before = scene_ids(server)

    @FUZZ
    @given(case=cases(target, method, path))
    def fuzz(case: Case) -> None:
        if (method, path) not in GUARDED:
            check_answer(server, case, AS_GENERATED, None)
            return
        check_answer(server, case, AS_GENERATED, {401, 403})  # whatever header the fuzzer made up
        check_answer(server, case, None, {401})
        check_answer(server, case, f"Bearer not-{TOKEN}", {403})

    fuzz()
    assert scene_ids(server) == before
    assert server.process.poll() is None, server.log()


def test_an_upload_with_the_token_that_is_no_checkpoint_is_refused(target: FuzzTarget) -> None:
    """With the right token the body is read and checked: whatever the fuzzer sends is a 4xx."""
    server = target.server
    before = scene_ids(server)

    @FUZZ
    @given(case=cases(target, "PUT", "/api/scenes/{scene_id}"))
    def fuzz(case: Case) -> None:
        check_answer(server, case, f"Bearer {TOKEN}", set(range(400, 500)))

    fuzz()
    assert scene_ids(server) == before
