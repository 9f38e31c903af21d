"""The number of CPUs this process may use: the default of ``--jobs``.

``os.cpu_count()`` counts the machine's CPUs, not this process's share. Two limits apply:
the CPU affinity mask (``taskset``, a container's cpuset: ``os.sched_getaffinity``) and a
cgroup CPU quota (a container's ``--cpus``: ``cpu.max`` in cgroup v2, ``cpu.cfs_quota_us`` /
``cpu.cfs_period_us`` in v1), whose share ``quota / period`` is rounded up. The default is
the smaller of the two, at least 1.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

CGROUP_ROOT = Path("/sys/fs/cgroup")
PROC_CGROUP = Path("/proc/self/cgroup")


def affinity_cpus() -> int:
    """CPUs in this process's affinity mask (``os.cpu_count()`` where the platform has no mask)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except OSError:
        return None


def _share(quota: str | None, period: str | None) -> float | None:
    """``quota / period`` CPUs, or None for no limit (``max``, ``-1``) or unreadable values."""
    if quota is None or period is None or quota in ("max", "-1"):
        return None
    try:
        q, p = int(quota), int(period)
    except ValueError:
        return None
    return q / p if q > 0 and p > 0 else None


def cgroup_cpus(root: Path = CGROUP_ROOT, proc_cgroup: Path = PROC_CGROUP) -> float | None:
    """The CPU quota of this process's cgroup in CPUs (``1.5`` for ``--cpus 1.5``), or None if unlimited.

    cgroup v2: ``<root>/<path>/cpu.max`` (``"<quota> <period>"`` or ``"max <period>"``) for the
    process's ``0::<path>`` line, and its parents up to ``root`` (the tightest applies); cgroup v1:
    ``cpu.cfs_quota_us`` and ``cpu.cfs_period_us`` in ``<root>/cpu/<path>`` or ``<root>/cpu``.
    """
    root, lines = Path(root), (_read(Path(proc_cgroup)) or "").splitlines()
    shares: list[float] = []
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, path = parts
        rel = path.strip("/")
        if controllers == "":  # v2: the limit of every ancestor applies
            d = root / rel if rel else root
            while True:
                text = _read(d / "cpu.max")
                if text:
                    s = _share(*(text.split() + [None])[:2])
                    if s is not None:
                        shares.append(s)
                if d == root or root not in d.parents:
                    break
                d = d.parent
        elif "cpu" in controllers.split(","):  # v1
            for d in ((root / "cpu" / rel) if rel else root / "cpu", root / "cpu"):
                s = _share(_read(d / "cpu.cfs_quota_us"), _read(d / "cpu.cfs_period_us"))
                if s is not None:
                    shares.append(s)
                    break
    return min(shares) if shares else None


def available_cores(root: Path = CGROUP_ROOT, proc_cgroup: Path = PROC_CGROUP) -> int:
    """CPUs available to this process: its affinity mask, capped by its cgroup quota (rounded up), at least 1."""
    n = affinity_cpus()
    quota = cgroup_cpus(root, proc_cgroup)
    if quota is not None:
        n = min(n, math.ceil(quota))
    return max(1, n)
