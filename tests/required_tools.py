"""What a test run requires: CI names tools in ``VISNERF_TESTS_REQUIRE`` (``chromium,nginx``) so
that the tests needing them fail, not skip, where they are missing."""

import os

import pytest


def required(tool: str) -> bool:
    """Whether this run must have ``tool`` (``chromium``, ``nginx``): CI names them in
    ``VISNERF_TESTS_REQUIRE`` so that its tests fail, not skip, where the tool is missing."""
    return tool in os.environ.get("VISNERF_TESTS_REQUIRE", "").replace(" ", "").split(",")


def skip_unless_present(tool: str, present: bool, reason: str) -> None:
    """Skip (or, where the run requires ``tool``, fail) a test that needs a missing tool."""
    if present:
        return
    if required(tool):
        pytest.fail(f"{reason}, and this run requires it (VISNERF_TESTS_REQUIRE)")
    pytest.skip(reason)
