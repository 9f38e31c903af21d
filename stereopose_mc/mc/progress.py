"""Progress of a run between chunk ends: chunks count trial-steps, the driver turns them into trials.

A chunk's ``tick(n, label, lost)`` (``mc.trial.run_filter``: ``B`` per filter step, with the trials
that filter lost since its last call) adds to its own entries of a mapping (:class:`StepCounter`);
a thread of the driver (:class:`Ticker`) polls the sums and calls the run's
``progress(done, total, diverged)`` with whole trials and the lost trials of the finished chunks and of
the chunks in flight. Counting changes no result.
"""

from __future__ import annotations

import threading
import time
from typing import Callable, Iterable, Mapping

Progress = Callable[[int, int, dict], None]  # (trials done, total, diverged so far per filter)
PROXY_EVERY_S = 0.5  # a worker process sends its chunk's trial-step count to the driver at most this often


class StepCounter:
    """Trial-steps done so far by the chunks of a run, for progress between chunk ends.

    Each chunk owns one entry (its first trial -> its trial-steps so far), so the chunks never
    write the same entry and a write needs no lock: a plain dict for threads, a :class:`SharedSteps`
    for workers forked from the driver, a Manager's dict proxy for other processes (each write a
    round trip to the Manager: sent at most every ``PROXY_EVERY_S``). The driver polls :meth:`total`.
    """

    def __init__(self, steps: Mapping | None = None):
        self.steps = {} if steps is None else steps

    def total(self) -> int:
        """Trial-steps counted (the entries ``chunk key -> steps``; ``list`` copies the mapping at once, so a chunk
        adding its first entry meanwhile cannot break the sum)."""
        return int(sum(v for k, v in list(self.steps.items()) if not isinstance(k, tuple)))

    def lost(self, finished: set[int]) -> dict[str, int]:
        """Trials lost so far per filter by the chunks in flight (the entries ``(chunk key, filter) -> lost``), the
        chunks ``finished`` left out (their own counts are the driver's)."""
        out: dict[str, int] = {}
        for k, v in list(self.steps.items()):
            if isinstance(k, tuple) and k[0] not in finished:
                out[k[1]] = out.get(k[1], 0) + int(v)
        return out

    class _Tick:
        def __init__(self, steps: Mapping, key: int, every_s: float):
            self.steps, self.key, self.every_s, self.n, self.sent_at = steps, key, every_s, 0, time.perf_counter()
            self.lost: dict[str, int] = {}
            self.sent_lost: dict[str, int] = {}

        def __call__(self, n: int, label: str | None = None, lost: int = 0) -> None:
            """``n`` more trial-steps done; ``lost`` more trials lost by the filter ``label`` (the chunk may run a
            filter over its trials in several calls: a dispersed target's groups)."""
            self.n += n
            if label is not None:
                self.lost[label] = self.lost.get(label, 0) + lost
            if self.every_s <= 0 or time.perf_counter() - self.sent_at >= self.every_s:
                self.flush()

        def flush(self) -> None:
            for label, v in self.lost.items():  # (only what changed: each write to a proxy is a round trip)
                if self.sent_lost.get(label) != v:
                    self.steps[(self.key, label)] = v
                    self.sent_lost[label] = v
            self.steps[self.key] = self.n
            self.sent_at = time.perf_counter()

    @classmethod
    def tick_of(cls, steps: Mapping, key: int, every_s: float = 0.0) -> StepCounter._Tick:
        """The ``tick(n)`` of the chunk whose first trial is ``key``."""
        return cls._Tick(steps, key, every_s)


class SharedSteps:
    """:class:`StepCounter`'s mapping in memory shared with the workers forked after it is made.

    A fixed entry per chunk key and per ``(chunk key, filter label)``, all 0 at first, each an
    int64 slot of one anonymous shared mapping (``multiprocessing.RawArray``, inherited through
    the fork): a worker's write is a store into its own slots, the driver's read a copy of all.
    A key it was not made with is a ``KeyError`` (a chunk or a filter the run does not have).
    """

    def __init__(self, keys: Iterable[int], labels: Iterable[str]):
        import multiprocessing

        keys, labels = [int(k) for k in keys], list(dict.fromkeys(labels))
        slots: list[int | tuple[int, str]] = [*keys, *((k, label) for k in keys for label in labels)]
        self._slot = {key: i for i, key in enumerate(slots)}
        self._values = multiprocessing.get_context("fork").RawArray("q", max(1, len(slots)))

    def __setitem__(self, key: int | tuple[int, str], value: int) -> None:
        self._values[self._slot[key]] = int(value)

    def __getitem__(self, key: int | tuple[int, str]) -> int:
        return int(self._values[self._slot[key]])

    def items(self) -> list[tuple[int | tuple[int, str], int]]:
        values = self._values[:]  # (one copy: the slots as they are now)
        return [(key, int(values[i])) for key, i in self._slot.items()]


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
        self.finished: set[int] = set()  # the finished chunks' keys (first trials): their lost counts are in diverged
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

    def _diverged(self) -> dict[str, int]:
        """Lost trials per filter: the finished chunks', and the chunks' in flight so far."""
        out = dict(self.diverged)
        if self.steps is not None:
            try:
                flight = self.steps.lost(self.finished)
            except (OSError, EOFError):  # the Manager is gone at the end of a run
                flight = {}
            for f, d in flight.items():
                out[f] = out.get(f, 0) + d
        return out

    def report(self) -> None:
        if self.progress is not None:
            with self._lock:
                self.progress(self._trials(), self.total, self._diverged())

    def chunk_done(self, n: int, diverged_by: dict[str, int], key: int | None = None) -> None:
        """A chunk of ``n`` trials ended with ``diverged_by`` lost per filter; ``key``: its first trial (its in-flight
        lost counts are then left out)."""
        with self._lock:
            if key is not None:
                self.finished.add(int(key))
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
