"""One rule for the upload token's file: the client finds what the server wrote, and a named file
that cannot be read is an error naming it on both sides."""

from pathlib import Path

import pytest

from visnerf.token_file import TOKEN_FILE_NAME, default_state_dir, read_token_file
from visnerf.upload import UploadError, find_token
from visnerf_server.auth import resolve_token
from visnerf_server.settings import Settings


@pytest.fixture
def clean_env(monkeypatch, tmp_path):
    for name in ("VISNERF_TOKEN", "VISNERF_TOKEN_FILE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("VISNERF_STATE_DIR", str(tmp_path / "state"))
    return tmp_path


def test_the_client_finds_the_token_the_server_made(clean_env: Path) -> None:
    assert find_token() is None  # nothing written yet
    made = resolve_token(Settings())  # generated under VISNERF_STATE_DIR
    assert default_state_dir() == clean_env / "state"
    assert (clean_env / "state" / TOKEN_FILE_NAME).read_text().strip() == made
    assert find_token() == made
    assert find_token("given") == "given"


def test_a_named_file_that_cannot_be_read_is_named(clean_env: Path, monkeypatch) -> None:
    missing = clean_env / "nope"
    monkeypatch.setenv("VISNERF_TOKEN_FILE", str(missing))
    with pytest.raises(UploadError, match="cannot read the upload token file .*nope"):
        find_token()
    with pytest.raises(RuntimeError, match="cannot read the upload token file .*nope"):
        resolve_token(Settings())
    empty = clean_env / "empty"
    empty.write_text("  \n")
    monkeypatch.setenv("VISNERF_TOKEN_FILE", str(empty))
    with pytest.raises(UploadError, match="is empty"):
        find_token()
    with pytest.raises(ValueError, match="is empty"):
        read_token_file(empty)
    monkeypatch.setenv("VISNERF_TOKEN", " secret ")
    assert find_token() == "secret"  # the variable comes first
