"""Peak memory of a command and all its descendants (Linux ``/proc``).

Two measurements of one run:

- **sampled tree sum**: every ``interval`` seconds, the resident set (``VmRSS`` of
  ``/proc/<pid>/status``) summed over the process and every live descendant (found by
  walking the ``PPid`` links of all ``/proc/<pid>/stat``); the peak of those sums. Pages
  shared between processes (libraries, copy-on-write) are counted once per process, so
  this over-states the physical memory; the same walk also sums ``Pss`` (proportional
  set size, ``/proc/<pid>/smaps_rollup``), which splits shared pages among their users.
  A spike shorter than ``interval`` can be missed.
- **largest single process**: ``ru_maxrss`` of the ``rusage`` that ``os.wait4`` returns
  for the command, which Linux defines as the maximum RSS of the command itself and of
  every descendant it reaped (the largest one, not a sum), tracked by the kernel (no
  sampling gap).
"""

from __future__ import annotations

import os
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

KIB = 1024


def _children_map() -> dict[int, list[int]]:
    """``ppid -> [pid, ...]`` of every process now visible in ``/proc``."""
    out: dict[int, list[int]] = {}
    for p in Path("/proc").iterdir():
        if not p.name.isdigit():
            continue
        try:
            stat = (p / "stat").read_text()
        except OSError:
            continue
        # the command name (field 2) is in parentheses and may hold spaces
        ppid = int(stat[stat.rfind(")") + 2 :].split()[1])
        out.setdefault(ppid, []).append(int(p.name))
    return out


def descendants(pid: int) -> list[int]:
    """``pid`` and all its live descendants."""
    kids = _children_map()
    todo, seen = [pid], []
    while todo:
        p = todo.pop()
        seen.append(p)
        todo.extend(kids.get(p, []))
    return seen


def _status_kib(pid: int, key: str) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return 0


def _pss_kib(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return 0


@dataclass
class MemorySample:
    rss_kib: int
    pss_kib: int
    processes: int
    max_process_rss_kib: int


def sample_tree(pid: int) -> MemorySample:
    """RSS and PSS summed over ``pid`` and its descendants, now."""
    pids = descendants(pid)
    rss = [_status_kib(p, "VmRSS") for p in pids]
    pss = [_pss_kib(p) for p in pids]
    return MemorySample(sum(rss), sum(pss), sum(1 for r in rss if r > 0), max(rss, default=0))


@dataclass
class PeakMemory:
    """Peaks of one run (MiB) and how they were measured."""

    returncode: int
    wall_s: float
    tree_rss_mib: float  # peak of the sampled sum of RSS over the process tree
    tree_pss_mib: float  # peak of the sampled sum of PSS over the process tree
    max_processes: int  # most processes seen in the tree at once
    sampled_max_process_rss_mib: float  # largest single process RSS seen while sampling
    wait4_maxrss_mib: float  # ru_maxrss from wait4: largest single process (kernel-tracked)
    samples: int
    interval_s: float
    stdout: str
    stderr: str


def run_and_measure(cmd: list[str], interval_s: float = 0.1, env: dict | None = None,
                    cwd: Path | None = None) -> PeakMemory:  # fmt: skip
    """Run ``cmd`` to completion while sampling its process tree every ``interval_s``."""
    with tempfile.TemporaryFile("w+") as out_f, tempfile.TemporaryFile("w+") as err_f:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out_f, stderr=err_f, env=env, cwd=cwd)
        peak = {"rss": 0, "pss": 0, "n": 0, "proc": 0, "samples": 0}
        stop = threading.Event()

        def sampler() -> None:
            while not stop.is_set():
                s = sample_tree(proc.pid)
                peak["rss"] = max(peak["rss"], s.rss_kib)
                peak["pss"] = max(peak["pss"], s.pss_kib)
                peak["n"] = max(peak["n"], s.processes)
                peak["proc"] = max(peak["proc"], s.max_process_rss_kib)
                peak["samples"] += 1
                stop.wait(interval_s)

        th = threading.Thread(target=sampler, daemon=True)
        th.start()
        try:
            _, status, ru = os.wait4(proc.pid, 0)
            code = os.waitstatus_to_exitcode(status)
            proc.returncode = code  # reaped here, not by Popen
            ru_kib = ru.ru_maxrss  # Linux: KiB
        finally:
            stop.set()
            th.join()
        wall = time.perf_counter() - t0
        out_f.seek(0)
        err_f.seek(0)
        stdout, stderr = out_f.read(), err_f.read()
    return PeakMemory(code, wall, peak["rss"] / KIB, peak["pss"] / KIB, peak["n"], peak["proc"] / KIB, ru_kib / KIB,
                      peak["samples"], interval_s, stdout, stderr)  # fmt: skip
