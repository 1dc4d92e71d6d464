"""Process-wide thread settings."""

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from visnerf import runtime
from visnerf.runtime import pick_device


@pytest.fixture
def restore_threads(monkeypatch):
    monkeypatch.setattr(runtime, "_explicit_threads", None)
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_an_explicit_thread_count_survives_pick_device(restore_threads, monkeypatch) -> None:
    monkeypatch.setattr(runtime, "default_threads", lambda: 2)
    runtime.configure(1)
    pick_device("cpu")  # calls configure() without a count
    assert torch.get_num_threads() == 1


def test_visnerf_threads_holds_on_cuda_too(restore_threads, monkeypatch) -> None:
    """A GPU run's CPU work (ray draws, carving, images) takes the thread count it was given, not
    every core of the node (torch's default), so that several runs can share one node."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setenv("VISNERF_THREADS", "2")
    torch.set_num_threads(1)
    assert pick_device("cuda").type == "cuda"
    assert torch.get_num_threads() == 2
    torch.set_num_threads(1)
    assert pick_device("auto").type == "cuda"
    assert torch.get_num_threads() == 2


def test_without_an_explicit_count_the_default_is_used(restore_threads, monkeypatch) -> None:
    monkeypatch.setattr(runtime, "default_threads", lambda: 2)
    torch.set_num_threads(1)
    runtime.configure()
    assert torch.get_num_threads() == 2


def test_a_thread_count_below_one_is_rejected(restore_threads) -> None:
    with pytest.raises(ValueError, match="at least 1"):
        runtime.configure(0)


def test_keep_freed_blocks_applies_both_settings() -> None:
    """glibc's mallopt returns 0 for a value it cannot apply (a mmap threshold above 32 MiB, for
    one), so True means both settings took effect."""
    import sys

    if not sys.platform.startswith("linux"):
        pytest.skip("glibc only")
    assert runtime.keep_freed_blocks()
    assert runtime.KEEP_BLOCKS_BELOW <= 32 << 20


@pytest.mark.parametrize(("visnerf", "omp", "want"), [("3", "1", 3), (None, "1", 1), (None, " 4 ", 4), ("0", None, 1)])
def test_the_default_takes_visnerf_threads_then_omp_num_threads(monkeypatch, visnerf, omp, want) -> None:
    for name, value in (("VISNERF_THREADS", visnerf), ("OMP_NUM_THREADS", omp)):
        if value is None:
            monkeypatch.delenv(name, raising=False)
        else:
            monkeypatch.setenv(name, value)
    assert runtime.default_threads() == want


def test_without_either_variable_the_default_is_the_cores_this_process_may_use(monkeypatch) -> None:
    import os

    monkeypatch.delenv("VISNERF_THREADS", raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert runtime.default_threads() == len(os.sched_getaffinity(0))


def test_a_thread_variable_that_is_no_number_is_refused_by_name(monkeypatch) -> None:
    monkeypatch.delenv("VISNERF_THREADS", raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "two")
    with pytest.raises(ValueError, match="OMP_NUM_THREADS must be a whole number"):
        runtime.default_threads()


def _omp_spin_count(code: str, **env: str) -> str:
    """The spin count torch's libgomp took, from its own report (OMP_DISPLAY_ENV=VERBOSE)."""
    base = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    done = subprocess.run([sys.executable, "-c", code], env={**base, **env, "OMP_DISPLAY_ENV": "VERBOSE"},
                          capture_output=True, text=True, check=True)
    found = re.search(r"GOMP_SPINCOUNT = '(\d+)'", done.stderr)
    assert found, done.stderr
    return found.group(1)


def test_importing_visnerf_before_torch_stops_openmp_workers_spinning() -> None:
    assert _omp_spin_count("import visnerf.runtime") == "0"
    assert _omp_spin_count("import torch") != "0"  # libgomp's default spins: the check can tell


def test_a_wait_policy_the_user_set_is_kept() -> None:
    assert _omp_spin_count("import visnerf.runtime", OMP_WAIT_POLICY="ACTIVE") != "0"


def test_every_benchmark_imports_visnerf_before_torch() -> None:
    for script in sorted((Path(__file__).parents[2] / "bench").glob("*.py")):
        imports = [node for node in ast.parse(script.read_text()).body if isinstance(node, ast.Import | ast.ImportFrom)]
        first = imports[0]
        assert isinstance(first, ast.Import) and first.names[0].name == "visnerf", script.name
