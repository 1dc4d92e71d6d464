#!/usr/bin/env bash
# Set up .venv (CPU PyTorch from the local wheel store, the project and its test extras) and run the tests:
#   bash scripts/test.sh          lint, types and the tests that take seconds (not marked slow)
#   bash scripts/test.sh --slow   the end-to-end runs: training commands, server processes, the browser
# Further arguments go to pytest.
set -euo pipefail
marker="not slow"
if [ "${1:-}" = "--slow" ]; then marker="slow"; shift; fi
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then python3 -m venv .venv; fi
.venv/bin/python -m pip install -q --upgrade pip >/dev/null 2>&1 || true
.venv/bin/python -m pip install -q torch==2.13.0
.venv/bin/python -m pip install -q -e ".[test]"
if [ ! -x /usr/bin/chromium ] && [ "$(id -u)" = 0 ]; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) || echo "chromium not installed: browser tests will be skipped (or fail where VISNERF_TESTS_REQUIRE names chromium)"
fi
if ! command -v nginx >/dev/null && [ ! -x /usr/sbin/nginx ] && [ "$(id -u)" = 0 ]; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq nginx >/dev/null) || echo "nginx not installed: the replica tests will be skipped (or fail where VISNERF_TESTS_REQUIRE names nginx)"
fi
.venv/bin/ruff check model server tests bench
.venv/bin/mypy
.venv/bin/python -m pytest -m "$marker" "$@"
