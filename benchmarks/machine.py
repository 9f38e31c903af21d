"""What the benchmark ran on: CPU, cores, memory, Python, library versions, BLAS, load."""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path
from typing import Any

from .common import ROOT


def _cpuinfo() -> tuple[str, int | None]:
    """CPU model name and physical core count from /proc/cpuinfo (None when unknown)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or "unknown", None
    model, cores, phys = "unknown", set(), None
    for line in text.splitlines():
        key, _, val = line.partition(":")
        key, val = key.strip(), val.strip()
        if key == "model name" and model == "unknown":
            model = val
        elif key == "physical id":
            phys = val
        elif key == "core id":
            cores.add((phys, val))
    return model, (len(cores) or None)


def _mem_total_gib() -> float | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return int(line.split()[1]) / 2**20
    except OSError:
        pass
    return None


def blas_info() -> list[dict[str, Any]]:
    """The BLAS/OpenMP libraries loaded by numpy and scipy (threadpoolctl), or numpy's build config."""
    import numpy  # noqa: F401  (loads the BLAS)
    import scipy.linalg  # noqa: F401

    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return [{"note": "threadpoolctl not installed (pip install threadpoolctl)"}]
    keep = ("user_api", "internal_api", "prefix", "version", "num_threads", "threading_layer", "architecture")
    return [{k: d.get(k) for k in keep if k in d} for d in threadpool_info()]


def _version(mod: str) -> str:
    try:
        m = __import__(mod)
        return getattr(m, "__version__", "?")
    except ImportError:
        return "not installed"


def git_revision() -> str:
    """``git rev-parse --short HEAD`` (read-only); the working tree may differ from it."""
    try:
        cmd = ["git", "rev-parse", "--short", "HEAD"]
        r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=10)
        return r.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def machine_info() -> dict[str, Any]:
    """Everything the header prints, as a dict (also stored in the JSON output)."""
    model, phys = _cpuinfo()
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        affinity = os.cpu_count()
    return {
        "cpu": model,
        "logical_cpus": os.cpu_count(),
        "physical_cores": phys,
        "cpus_usable": affinity,
        "memory_gib": _mem_total_gib(),
        "os": f"{platform.system()} {platform.release()}",
        "python": f"{platform.python_implementation()} {platform.python_version()}",
        "numpy": _version("numpy"),
        "scipy": _version("scipy"),
        "filterpy": _version("filterpy"),
        "pandas": _version("pandas"),
        "pyarrow": _version("pyarrow"),
        "blas": blas_info(),
        "blas_env": {k: os.environ[k] for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
                     if k in os.environ},  # fmt: skip
        "git": git_revision(),
        "loadavg_start": os.getloadavg(),
    }


def format_machine(info: dict[str, Any]) -> str:
    """The header lines printed above the table."""
    mem = f"{info['memory_gib']:.1f} GiB" if info.get("memory_gib") else "unknown"
    blas = "; ".join(
        f"{b.get('internal_api', b.get('user_api', '?'))} {b.get('version', '')} ({b.get('user_api', '')}, "
        f"{b.get('num_threads', '?')} threads, {b.get('architecture', '')})"
        if "note" not in b else b["note"]
        for b in info["blas"]
    ) or "none reported"
    env = ", ".join(f"{k}={v}" for k, v in info.get("blas_env", {}).items()) or "unset"
    la = info.get("loadavg_start")
    le = info.get("loadavg_end")
    load = f"{la[0]:.2f} at start" + (f", {le[0]:.2f} at end" if le else "")
    return "\n".join([
        f"machine : {info['cpu']}; {info['logical_cpus']} logical CPUs "
        f"({info['physical_cores'] or '?'} physical cores, "
        f"{info['cpus_usable']} usable); memory {mem}; {info['os']}",
        f"python  : {info['python']}; numpy {info['numpy']}, scipy {info['scipy']}, filterpy {info['filterpy']}, "
        f"pandas {info['pandas']}, pyarrow {info['pyarrow']}",
        f"BLAS    : {blas}; thread env: {env}",
        f"load    : 1-min load average {load} (other processes share the machine when it exceeds 0)",
        f"code    : git {info['git']} (working tree may differ)",
    ])  # fmt: skip
