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
  sampling gap). Linux carries a process's high-water mark across ``fork``/``vfork`` +
  ``exec`` (``signal->maxrss`` takes the old address space's peak at ``exec``), so a
  command started directly from a big parent (the benchmark process after its in-process
  sections) would report the parent's peak. The command is therefore started by a small
  launcher interpreter (``LAUNCHER``, about 10 MiB), which waits for it and reports its
  ``ru_maxrss``; the launcher itself is left out of the sampled sums.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

KIB = 1024

# python -c LAUNCHER REPORT CMD...: run CMD, wait4 it, write "<exit code> <ru_maxrss KiB>" to REPORT
LAUNCHER = (
    "import os, subprocess, sys\n"
    "p = subprocess.Popen(sys.argv[2:])\n"
    "_, st, ru = os.wait4(p.pid, 0)\n"
    "code = p.returncode = os.waitstatus_to_exitcode(st)\n"
    "open(sys.argv[1], 'w').write(f'{code} {ru.ru_maxrss}')\n"
    "sys.exit(code if 0 <= code < 256 else 1)\n"
)


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


def sample_tree(pid: int, include_root: bool = True) -> MemorySample:
    """RSS and PSS summed over ``pid`` (unless ``include_root`` is False) and its descendants, now."""
    pids = descendants(pid)
    if not include_root:
        pids = [p for p in pids if p != pid]
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
    """Run ``cmd`` (through ``LAUNCHER``) to completion, sampling its process tree every ``interval_s``."""
    with tempfile.TemporaryDirectory() as td, tempfile.TemporaryFile("w+") as out_f, \
            tempfile.TemporaryFile("w+") as err_f:  # fmt: skip
        report = Path(td) / "wait4.txt"
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-c", LAUNCHER, str(report), *cmd], stdout=out_f, stderr=err_f,
                                env=env, cwd=cwd)  # fmt: skip
        peak = {"rss": 0, "pss": 0, "n": 0, "proc": 0, "samples": 0}
        stop = threading.Event()

        def sampler() -> None:
            while not stop.is_set():
                s = sample_tree(proc.pid, include_root=False)
                peak["rss"] = max(peak["rss"], s.rss_kib)
                peak["pss"] = max(peak["pss"], s.pss_kib)
                peak["n"] = max(peak["n"], s.processes)
                peak["proc"] = max(peak["proc"], s.max_process_rss_kib)
                peak["samples"] += 1
                stop.wait(interval_s)

        th = threading.Thread(target=sampler, daemon=True)
        th.start()
        try:
            code = proc.wait()
        finally:
            stop.set()
            th.join()
        wall = time.perf_counter() - t0
        try:
            rc, ru_kib = (int(v) for v in report.read_text().split())
        except (OSError, ValueError):
            rc, ru_kib = code if code else 1, 0
        out_f.seek(0)
        err_f.seek(0)
        stdout, stderr = out_f.read(), err_f.read()
    return PeakMemory(rc, wall, peak["rss"] / KIB, peak["pss"] / KIB, peak["n"], peak["proc"] / KIB, ru_kib / KIB,
                      peak["samples"], interval_s, stdout, stderr)  # fmt: skip
