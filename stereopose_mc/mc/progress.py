"""Progress of a run between chunk ends: chunks count trial-steps, the driver turns them into trials.

A chunk's ``tick(n)`` (``mc.trial.run_filter``: ``B`` per filter step) adds to its own entry of a
mapping (:class:`StepCounter`); a thread of the driver (:class:`Ticker`) polls the sum and calls
the run's ``progress(done, total, diverged)`` with whole trials. Counting changes no result.
"""

from __future__ import annotations

import threading
import time
from typing import Callable, Mapping

Progress = Callable[[int, int, dict], None]  # (trials done, total, diverged so far per filter)
PROXY_EVERY_S = 0.5  # a worker process sends its chunk's trial-step count to the driver at most this often


class StepCounter:
    """Trial-steps done so far by the chunks of a run, for progress between chunk ends.

    Each chunk owns one entry (its first trial -> its trial-steps so far), so the chunks never
    write the same entry and a write needs no lock: a plain dict for threads, a Manager's dict
    proxy for processes (each write a round trip to the Manager: sent at most every
    ``PROXY_EVERY_S``). The driver polls :meth:`total`.
    """

    def __init__(self, steps: Mapping | None = None):
        self.steps = {} if steps is None else steps

    def total(self) -> int:
        return int(sum(self.steps.values()))

    class _Tick:
        def __init__(self, steps: Mapping, key: int, every_s: float):
            self.steps, self.key, self.every_s, self.n, self.sent_at = steps, key, every_s, 0, time.perf_counter()

        def __call__(self, n: int) -> None:
            self.n += n
            if self.every_s <= 0 or time.perf_counter() - self.sent_at >= self.every_s:
                self.flush()

        def flush(self) -> None:
            self.steps[self.key] = self.n
            self.sent_at = time.perf_counter()

    @classmethod
    def tick_of(cls, steps: Mapping, key: int, every_s: float = 0.0) -> StepCounter._Tick:
        """The ``tick(n)`` of the chunk whose first trial is ``key``."""
        return cls._Tick(steps, key, every_s)



class Ticker:
    """The run's progress: finished chunks, and between chunk ends the trial-steps of the chunks in flight.

    ``progress(done, total, diverged)`` gets whole trials: those of the finished chunks, or (if
    more) the trials the counted trial-steps amount to (``per_trial`` trial-steps each: steps x
    filters). A thread polls the counter every ``every_s``; calls never overlap.
    """

    def __init__(self, progress: Progress | None, start: int, total: int, per_trial: int, diverged: dict[str, int],
                 every_s: float = 0.5):  # fmt: skip
        self.progress, self.start, self.done, self.total = progress, start, start, total
        self.per_trial, self.diverged, self.every_s = max(1, per_trial), diverged, every_s
        self.steps: StepCounter | None = None
        self._lock, self._stop = threading.Lock(), threading.Event()
        self._thread: threading.Thread | None = None

    def counter(self, steps: Mapping | None) -> StepCounter:
        self.steps = StepCounter(steps)
        return self.steps

    def _trials(self) -> int:
        if self.steps is None:
            return self.done
        try:
            counted = self.steps.total()
        except (OSError, EOFError):  # the Manager is gone at the end of a run: the chunks' own count stands
            return self.done
        return max(self.done, min(self.total, self.start + counted // self.per_trial))

    def report(self) -> None:
        if self.progress is not None:
            with self._lock:
                self.progress(self._trials(), self.total, dict(self.diverged))

    def chunk_done(self, n: int, diverged_by: dict[str, int]) -> None:
        with self._lock:
            self.done += n
            for f, d in diverged_by.items():
                self.diverged[f] = self.diverged.get(f, 0) + d
        self.report()

    def _poll(self) -> None:
        while not self._stop.wait(self.every_s):
            self.report()

    def __enter__(self) -> Ticker:
        if self.progress is not None:
            self._thread = threading.Thread(target=self._poll, name="spmc-progress", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
