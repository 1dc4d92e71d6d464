"""The cores a process may use: the CPU quota of the cgroup read from fake ``/sys/fs/cgroup`` and
``/proc/self/cgroup`` files, and the fallback to the usable cores; the thread rule on top of it."""

from pathlib import Path

import pytest

from visnerf import cpu_quota, runtime
from visnerf.cpu_quota import cgroup_cpu_quota
from visnerf.cpu_quota import quota_cores as default_threads


def write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


@pytest.fixture
def cgroup(tmp_path: Path) -> tuple[Path, Path]:
    """(root of a fake cgroup mount, fake /proc/self/cgroup)."""
    return tmp_path / "sys_fs_cgroup", tmp_path / "proc_self_cgroup"


@pytest.fixture
def eight_cores(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cpu_quota, "usable_cores", lambda: 8)


@pytest.mark.parametrize(
    ("cpu_max", "quota", "threads"),
    [("200000 100000\n", 2.0, 2), ("max 100000\n", None, 8), ("150000 100000", 1.5, 1), ("50000 100000", 0.5, 1),
     ("1600000 100000", 16.0, 8), ("garbage", None, 8)],
)
def test_cgroup_v2_cpu_max(cgroup, eight_cores, cpu_max: str, quota: float | None, threads: int) -> None:
    root, proc = cgroup
    write(proc, "0::/\n")
    write(root / "cpu.max", cpu_max)
    assert cgroup_cpu_quota(root, proc) == quota
    assert default_threads(root, proc) == threads


def test_cgroup_v2_the_smallest_limit_on_the_way_up_applies(cgroup, eight_cores) -> None:
    root, proc = cgroup
    write(proc, "0::/system.slice/visnerf.service\n")
    write(root / "system.slice" / "visnerf.service" / "cpu.max", "max 100000")
    write(root / "system.slice" / "cpu.max", "300000 100000")
    assert cgroup_cpu_quota(root, proc) == 3.0
    assert default_threads(root, proc) == 3


def test_cgroup_v1_quota_and_period(cgroup, eight_cores) -> None:
    root, proc = cgroup
    write(proc, "4:memory:/docker/abc\n2:cpu,cpuacct:/docker/abc\n")
    write(root / "cpu,cpuacct" / "cpu.cfs_quota_us", "400000\n")  # the container's view: its own at the root
    write(root / "cpu,cpuacct" / "cpu.cfs_period_us", "100000\n")
    assert cgroup_cpu_quota(root, proc) == 4.0
    assert default_threads(root, proc) == 4
    write(root / "cpu,cpuacct" / "cpu.cfs_quota_us", "-1\n")  # no limit
    assert cgroup_cpu_quota(root, proc) is None
    assert default_threads(root, proc) == 8


def test_no_cgroup_files_means_the_usable_cores(cgroup, eight_cores) -> None:
    root, proc = cgroup
    assert cgroup_cpu_quota(root, proc) is None
    assert default_threads(root, proc) == 8


def test_threads_come_from_the_environment_else_the_quota(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(runtime, "quota_cores", lambda: 3)
    for name in ("VISNERF_THREADS", "OMP_NUM_THREADS"):
        monkeypatch.delenv(name, raising=False)
    assert runtime.default_threads() == runtime.available_cores() == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert runtime.default_threads() == 1
    monkeypatch.setenv("VISNERF_THREADS", "2")
    assert runtime.default_threads() == 2
