"""The cores this process may use: its CPU affinity, capped by the CPU quota of the cgroup it runs
in (a container's ``--cpus``). ``runtime.default_threads`` gives torch that many threads, in
training and in the server.

torch's default is every core of the machine, which in a container limited to two CPUs means
threads that mostly wait for their share (throttled by the CFS quota): slower steps and frames.

cgroup v2: ``cpu.max`` holds ``"<quota> <period>"`` in microseconds, or ``"max <period>"`` for no
limit, in the process's own cgroup and each one above it (the smallest limit applies). cgroup v1:
``cpu.cfs_quota_us`` (-1: no limit) and ``cpu.cfs_period_us`` in the ``cpu`` controller's folder.
A quota of 1.5 CPUs gives one thread: a second one would be throttled half the time.
"""

import math
import os
from collections.abc import Iterator
from pathlib import Path

CGROUP_ROOT = Path("/sys/fs/cgroup")
PROC_SELF_CGROUP = Path("/proc/self/cgroup")


def _read(path: Path) -> str | None:
    try:
        return path.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError):
        return None


def _own_cgroups(proc_cgroup: Path) -> dict[str, str]:
    """Controller list (``""`` for v2) -> the process's cgroup path, from ``/proc/self/cgroup``."""
    paths: dict[str, str] = {}
    for line in (_read(proc_cgroup) or "").splitlines():
        parts = line.split(":", 2)
        if len(parts) == 3:
            paths[parts[1]] = parts[2]
    return paths


def _folders_up(base: Path, cgroup_path: str | None) -> Iterator[Path]:
    """``base/cgroup_path`` and each folder above it up to ``base`` (inside a container whose
    cgroup namespace hides the path, just ``base``)."""
    parts = [p for p in (cgroup_path or "").split("/") if p and p not in (".", "..")]
    for n in range(len(parts), -1, -1):
        yield base.joinpath(*parts[:n])


def _v2_quota(text: str | None) -> float | None:
    fields = (text or "").split()
    if len(fields) != 2 or fields[0] == "max":
        return None
    try:
        quota, period = int(fields[0]), int(fields[1])
    except ValueError:
        return None
    return quota / period if quota > 0 and period > 0 else None


def _v1_quota(folder: Path) -> float | None:
    try:
        quota = int(_read(folder / "cpu.cfs_quota_us") or "-1")
        period = int(_read(folder / "cpu.cfs_period_us") or "0")
    except ValueError:
        return None
    return quota / period if quota > 0 and period > 0 else None


def cgroup_cpu_quota(root: Path = CGROUP_ROOT, proc_cgroup: Path = PROC_SELF_CGROUP) -> float | None:
    """CPUs the process's cgroup may use (quota / period; 2.0 for ``"200000 100000"``), or None
    when no quota is set or none can be read."""
    own = _own_cgroups(proc_cgroup)
    quotas = [_v2_quota(_read(folder / "cpu.max")) for folder in _folders_up(root, own.get(""))]
    v1_path = next((path for controllers, path in own.items() if "cpu" in controllers.split(",")), None)
    for name in ("cpu", "cpu,cpuacct", "cpuacct,cpu"):
        quotas += [_v1_quota(folder) for folder in _folders_up(root / name, v1_path)]
    found = [q for q in quotas if q is not None]
    return min(found) if found else None


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity), or the machine's count."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def quota_cores(root: Path = CGROUP_ROOT, proc_cgroup: Path = PROC_SELF_CGROUP) -> int:
    """The cgroup's CPU quota rounded down (at least 1, at most the usable cores), else the usable
    cores."""
    cores = usable_cores()
    quota = cgroup_cpu_quota(root, proc_cgroup)
    if quota is None:
        return cores
    return max(1, min(cores, math.floor(quota + 1e-9)))
