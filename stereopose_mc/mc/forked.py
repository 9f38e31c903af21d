"""A run's chunks in worker processes forked from the driver: the default for the compiled kernels on Linux.

Two threads of one process running the compiled kernels share more than the GIL: OpenBLAS's pool of
work buffers (a ``dgemm`` takes one from the pool and gives it back, so the two threads pack into each
other's buffers), the reference counts of the objects both touch, the allocator's bookkeeping. Measured
on a 2-core machine (case B, 1,000 trials, chunks of 250): the threads' chunks took 1.9-2.1 s each for
minutes at a time and 2.2-2.7 s at others, while two processes running the same chunks at the same
moments took 1.8-2.1 s (``perf``, a slow run against a fast one: OpenBLAS's packing copies and its
``blas_memory_alloc`` / ``free``, ``pthread_mutex_lock`` / ``unlock`` and the kernel's share grew, the
compiled kernels' own code did not); the whole run 4.3-5.7 s on threads, 4.4-4.8 s on forked workers. A forked
worker starts with everything the driver has loaded (modules, the scenario's prepared truth, the
kernels Numba has loaded) and computes its chunks with nothing shared but the files it writes.

:func:`outputs` runs ``job(i)`` for the chunks ``i`` in ``jobs`` workers of a
``ProcessPoolExecutor`` whose processes are forked (not spawned: nothing is imported again, and the
job, a closure of the driver's, reaches them through the fork, not through pickling); their results
come back pickled (a chunk's Arrow tables). A worker ignores SIGINT: on Ctrl-C the driver stops
waiting, cancels the chunks not started and waits for the running ones, which finish and write their
files (a resume keeps them), as the threads' chunks do. A worker that dies (killed, out of memory)
is a :class:`WorkerDied` naming the chunks in flight; the chunks that finished are kept. A worker
dies with the driver (``PR_SET_PDEATHSIG``: killed, even by SIGKILL, the driver leaves no worker
writing into its run directory) and closes its copies of the driver's run locks
(``rundir.runlock``), which the driver alone holds.

Linux only (:func:`available`): macOS's system libraries are not safe to use in a forked child,
Windows has no fork. Python 3.12 and newer warn that forking a process that has threads may deadlock
the child; the driver's threads at that moment are OpenBLAS's idle pools (which OpenBLAS itself
stops and restarts around a fork) and the progress thread, which holds no lock a worker takes, so
that warning is silenced for the fork only.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import warnings
from typing import Callable, Iterable, Sequence, TypeVar

from ..rundir import runlock  # (imported here: a worker imports nothing)

T = TypeVar("T")

_JOB: Callable[[int], object] | None = None  # in a worker: the job it inherited from the driver
_STATE = None  # in a worker: the chunks' states, shared with the driver (RUNNING, DONE)
RUNNING, DONE = 1, 2


class WorkerDied(RuntimeError):
    """A worker process ended while it computed a chunk: ``chunks``, the chunks then in flight (their indices or
    names; the pool stops every worker when one dies, so which of them it was is not known)."""

    def __init__(self, chunks: list, reason: str):
        super().__init__(chunks, reason)
        self.chunks, self.reason = chunks, reason

    def __str__(self) -> str:
        which = " or ".join(str(c) for c in self.chunks) or "?"
        return f"a worker process died while computing chunk {which} ({self.reason})"


def available() -> bool:
    """True where chunks can run in forked workers: Linux, with the ``fork`` start method."""
    return sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods()


PR_SET_PDEATHSIG = 1  # prctl(2): the signal a process gets when the thread that forked it ends


def _die_with_parent(parent: int) -> None:
    """SIGKILL to this process when its parent ends (Linux's ``prctl(PR_SET_PDEATHSIG)``), or exit now if the
    parent already has. (Where ``prctl`` fails, the watch that the ``init`` of :func:`outputs` may start stays.)"""
    import ctypes

    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:  # the parent ended before the call
        os._exit(1)


def _start(job: Callable[[int], object], init: Callable[[], None] | None, parent: int, state) -> None:
    """A worker's initializer: dies with the driver, holds none of its run locks, ignores SIGINT (the driver
    decides), keeps the job and the chunks' states; then ``init()``."""
    global _JOB, _STATE
    _die_with_parent(parent)
    runlock.forget_inherited()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _JOB, _STATE = job, state
    if init is not None:
        init()


def _call(i: int) -> object:
    """In a worker: the inherited job on chunk ``i``, its state kept in the shared array."""
    assert _JOB is not None and _STATE is not None, "not a forked worker of forked.outputs"
    _STATE[i] = RUNNING
    out = _JOB(i)
    _STATE[i] = DONE
    return out


def outputs(job: Callable[[int], T], n: int, jobs: int, init: Callable[[], None] | None = None,
            names: Sequence[str] | None = None) -> Iterable[T]:  # fmt: skip
    """``job(i)`` for ``i`` in ``range(n)`` in ``jobs`` forked workers, yielded as they finish (any order).

    ``init()`` runs once in each worker before its first chunk. An exception raised by ``job`` is
    raised here (its traceback from the worker chained); a worker that dies is :class:`WorkerDied`
    naming the chunks then in flight (``names[i]``, if given, for chunk ``i``). Leaving early (an
    error, Ctrl-C, the consumer stopping) cancels the chunks not started and waits for the running ones.
    """
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    if n == 0:
        return
    ctx = multiprocessing.get_context("fork")
    state = ctx.RawArray("b", n)  # each chunk's: 0 (not started), RUNNING, DONE
    pool = ProcessPoolExecutor(max_workers=max(1, min(jobs, n)), mp_context=ctx, initializer=_start,
                               initargs=(job, init, os.getpid(), state))  # fmt: skip
    try:
        with warnings.catch_warnings():  # Python >= 3.12: "This process ... is multi-threaded, use of fork() ..."
            warnings.filterwarnings("ignore", message=r".*fork\(\).*", category=DeprecationWarning)
            futures = {pool.submit(_call, i): i for i in range(n)}  # the first submit forks every worker
        for f in as_completed(futures):
            try:
                yield f.result()
            except BrokenProcessPool:
                flight = [i for i in range(n) if state[i] == RUNNING]
                raise WorkerDied([i if names is None else names[i] for i in flight], "killed, or out of memory?"
                                 ) from None  # fmt: skip
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
