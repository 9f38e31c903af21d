"""Progress reporting: a rich bar on a terminal, plain periodic lines otherwise."""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager
from typing import Iterator



def diverged_text(diverged: dict[str, int]) -> str:
    """``{"iekf": 1, "ekf": 12}`` -> ``iekf 1, ekf 12`` (finished chunks of a resumed run included)."""
    return ", ".join(f"{k} {v}" for k, v in diverged.items()) or "0"


def duration_text(seconds: float) -> str:
    """``48 s``, ``1 min 48 s``, ``2 h 05 min`` (whole seconds; minutes past an hour)."""
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def eta_text(elapsed_s: float, done: int, total: int, at_most: bool = False) -> str:
    """``12 s elapsed, about 1 min 48 s left``: the mean time of the ``done`` steps (of ``total``) times the steps
    left; ``at_most``: ``at most`` (a search that may end before its budget); only the elapsed time once all are
    done, and nothing before the first."""
    if done <= 0:
        return ""
    text = f"{duration_text(elapsed_s)} elapsed"
    if done < total:
        text += f", {'at most' if at_most else 'about'} {duration_text(elapsed_s / done * (total - done))} left"
    return text


class _Plain:
    """Lines like ``caseB: 300/1000 trials (30%), 12.1 trials/s, ETA 58 s, lost iekf 1, ekf 3``."""

    def __init__(self, label: str, every_s: float = 10.0):
        self.label, self.every_s = label, every_s
        self.t0 = time.perf_counter()
        self.last = -1e9
        self.start_done: int | None = None
        self.last_done = -1
        self.last_div: dict[str, int] | None = None

    def __call__(self, done: int, total: int, diverged: dict[str, int]) -> None:
        now = time.perf_counter()
        first = self.start_done is None
        if first:
            self.start_done = done
        if not first and done < total and now - self.last < self.every_s:
            return
        # every trial-step can be counted before the last chunks have returned their lost counts: at 100 % a line
        # is printed again when those change, so the last line has every chunk's
        if done == total and self.last_done == total and diverged == self.last_div:
            return
        self.last_done, self.last_div = done, dict(diverged)
        self.last = now
        el = now - self.t0
        rate = (done - self.start_done) / el if el > 0 else 0.0
        eta = f"{(total - done) / rate:.0f} s" if rate > 0 else "?"
        pct = 100.0 * done / total if total else 100.0
        div = diverged_text(diverged)
        print(f"{self.label}: {done}/{total} trials ({pct:.0f}%), {rate:.1f} trials/s, ETA {eta}, lost {div}",
              file=sys.stderr, flush=True)  # fmt: skip


BAR_TEXT_WIDTH = 64  # the columns that keep their whole text (``200/200 trials 51.0/s ETA 0:00:03 0:00:02 lost ...``)


def bar_columns(label: str, width: int) -> list:
    """The rich bar's columns on a terminal of ``width`` columns: the label, the bar, ``done/total trials``, the
    rate, ``ETA``, the remaining and elapsed times, ``lost iekf 1, ekf 3``. The counts, times and lost counts keep
    their whole text; the label and the bar get what they leave (at least 8 and 5 columns, the bar at most 40): on
    an 80-column terminal a sweep point's long label is cut with an ellipsis, not the counts or the ETA."""
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn
    from rich.table import Column

    def whole() -> Column:
        return Column(no_wrap=True)

    room = max(13, width - BAR_TEXT_WIDTH)
    label_width = min(len(label), max(8, room - 10))
    return [TextColumn(f"[bold]{label}", table_column=Column(no_wrap=True, overflow="ellipsis", max_width=label_width)),
            BarColumn(bar_width=max(5, min(40, room - label_width - 1))),
            MofNCompleteColumn(table_column=whole()), TextColumn("trials", table_column=whole()),
            TextColumn("{task.fields[rate]}", table_column=whole()), TextColumn("ETA", table_column=whole()),
            TimeRemainingColumn(table_column=whole()), TimeElapsedColumn(table_column=whole()),
            TextColumn("lost {task.fields[div]}", table_column=whole())]  # fmt: skip


@contextmanager
def progress_reporter(label: str, quiet: bool = False) -> Iterator:
    """Yield a ``progress(done, total, diverged)`` callable for the engine."""
    if quiet:
        yield None
        return
    from rich.console import Console  # here, not at import: a --quiet run never loads rich
    from rich.progress import Progress

    console = Console(stderr=True)
    if not console.is_terminal:
        yield _Plain(label)
        return
    with Progress(*bar_columns(label, console.width), console=console, transient=False) as bar:
        task = bar.add_task(label, total=None, rate="", div="")
        t0 = time.perf_counter()
        first: list[int] = []

        def update(done: int, total: int, diverged: dict[str, int]) -> None:
            if not first:
                first.append(done)
            el = time.perf_counter() - t0
            rate = (done - first[0]) / el if el > 0 else 0.0
            bar.update(task, total=total, completed=done, rate=f"{rate:.1f}/s", div=diverged_text(diverged))

        yield update


class _FigureLine:
    """``caseB: writing report figure 3 (hist-iekf), 2 s``: one line rewriting itself on a terminal,
    else a line per figure."""

    def __init__(self, label: str):
        self.label, self.n, self.t0 = label, 0, time.perf_counter()
        self.tty = sys.stderr.isatty()

    def __call__(self, key: str) -> None:
        self.n += 1
        line = f"{self.label}: writing report figure {self.n} ({key}), {time.perf_counter() - self.t0:.0f} s"
        print(("\r" + line.ljust(78)) if self.tty else line, end="" if self.tty else "\n", file=sys.stderr, flush=True)

    def __enter__(self) -> "_FigureLine":
        return self

    def __exit__(self, *exc) -> None:
        if self.tty and self.n:
            print(file=sys.stderr, flush=True)


@contextmanager
def figure_progress(label: str, quiet: bool = False) -> Iterator:
    """Yield a ``progress(figure_key)`` callable for report writing (``None`` when quiet)."""
    if quiet:
        yield None
        return
    with _FigureLine(label) as line:
        yield line
