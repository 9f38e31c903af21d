"""The cyclic garbage collector during a run's start-up: paused, then the start-up's objects frozen.

A run's start-up (importing Numba and the kernel modules, the scenario's set-up, the shared truth)
creates some 100,000 objects that live as long as the process. With the collector on, the full
collections that this growth triggers traverse all of them, twice in case B's start-up: 0.08-0.1 s
of its serial part (``docs/performance.md``). :func:`paused` turns the collector off for the
start-up; the engine then calls the function it yields once the start-up is done, which moves every
object so far into the permanent generation (``gc.freeze``: ignored by later collections) and turns
the collector on again for the chunks, so that garbage in reference cycles is collected during the run
as before.

Once per process: later runs of the same process (a sweep, a tuning study, the tests) find the
imports done and frozen and leave the collector as it is. Nothing is paused where the collector is
already off (the caller's choice).
"""

from __future__ import annotations

import contextlib
import gc
import threading
from typing import Callable, Iterator

_lock = threading.Lock()
_settled = False  # the start-up's objects are frozen (once per process)


@contextlib.contextmanager
def paused() -> Iterator[Callable[[], None]]:
    """Pause the collector for a run's start-up; yield ``settle()``, which freezes what exists and resumes it.

    ``settle`` may be called more than once (the later calls do nothing). Leaving the block without it (an
    error during the start-up) resumes the collector without freezing.
    """
    with _lock:
        active = not _settled and gc.isenabled()
        if active:
            gc.disable()
    on = [active]

    def settle() -> None:
        global _settled
        with _lock:
            if on[0]:
                on[0] = False
                _settled = True
                gc.freeze()
                gc.enable()

    try:
        yield settle
    finally:
        with _lock:
            if on[0]:
                on[0] = False
                gc.enable()
