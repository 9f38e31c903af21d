"""Will a run fit? The memory the driver needs for a trial count, against the machine's.

The chunks are bounded (``--chunk-size`` trials at a time per worker) and the time series
is streamed, but the driver holds the merged per-trial table (one row per trial x filter)
and a few trial-index arrays in memory. ``spmc validate`` and ``spmc run`` refuse a trial
count whose estimate exceeds the machine's physical memory, with both numbers.
"""

from __future__ import annotations

import os

ROW_BYTES = 300  # one trials-table row in pandas (about 25 columns, two strings)
PEAK_FACTOR = 3  # concatenation and sorting copy the table
INDEX_BYTES = 3 * 8  # int64 trial indices: all, done, to do


def run_memory_bytes(trials: int, filters: int) -> int:
    """Estimated peak driver memory of a run with ``trials`` trials and ``filters`` filters."""
    return int(trials) * (max(1, filters) * ROW_BYTES * PEAK_FACTOR + INDEX_BYTES)


def physical_memory_bytes() -> int | None:
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return None


def human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB"):
        if n < 1024 or unit == "EiB":
            return f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} EiB"  # pragma: no cover


def memory_problem(trials: int, filters: int, memory: int | None = None) -> str | None:
    """Why ``trials`` cannot run on this machine, or None."""
    memory = physical_memory_bytes() if memory is None else memory
    need = run_memory_bytes(trials, filters)
    if memory is None or need <= memory:
        return None
    return (f"{trials} trials x {filters} filter(s) need about {human_bytes(need)} of memory for the merged "
            f"per-trial table, more than this machine's {human_bytes(memory)}; split the campaign into runs "
            f"of at most {memory // run_memory_bytes(1, filters)} trials")  # fmt: skip
