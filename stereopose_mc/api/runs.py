"""Monte Carlo runs in Python: :func:`run`, :func:`resume`, :class:`Run` (a run directory's tables as
DataFrames), :func:`report` (what ``spmc report`` does for a list of paths)."""

from __future__ import annotations

import functools
import json
import sys
import tempfile
from collections.abc import Mapping
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, ContextManager

from ..config.schema import Scenario
from ..mc import engine
from ..rundir import percentiles, tables
from ..rundir.runlock import locked
from ..rundir.store import RunDirError
from .errors import SpmcError
from .scenarios import as_scenario

BACKENDS = ("auto", "fork", "threading", "loky", "dask")
KERNELS = ("numpy", "compiled")

Progress = Callable[[int, int, dict], None]  # (trials done, total, diverged so far per filter)
FigureProgress = Callable[[str], None]  # called with each figure's key as it is drawn

if TYPE_CHECKING:  # pandas (~0.25 s) is imported when a table is read, never by a run
    import pandas as pd


def _export():
    from ..outputs import export

    return export


@dataclass(frozen=True)
class Rerun:
    """One trial recomputed from its seed: its trials rows, full time series, and whether it matches the run."""

    trial: int
    trials: pd.DataFrame
    timeseries: pd.DataFrame
    identical: bool
    lines: list[str] = field(default_factory=list)


class Run:
    """A run directory (``spmc run``'s output) read as pandas DataFrames.

    ``trials``, ``timeseries``, ``percentiles`` and ``timing`` are read once, on first use; each
    DataFrame has the units of its columns in ``df.attrs["units"]`` (from the Parquet field
    metadata). ``manifest`` is the run's ``manifest.json`` as a dict (nested: version, seed,
    filters, backend, per-chunk timings); ``chunks`` its per-chunk timings as a DataFrame.
    """

    def __init__(self, path: str | Path, result: engine.RunResult | None = None):
        self.path = Path(path)
        self._result = result

    @classmethod
    def open(cls, path: str | Path) -> Run:
        """An existing run directory; :class:`SpmcError` if ``path`` is not one."""
        path = Path(path)
        try:
            m = json.loads((path / "manifest.json").read_bytes())
        except (OSError, ValueError):  # not JSON, not UTF-8
            raise SpmcError(f"{path}: not a run directory (no readable manifest.json)") from None
        if not isinstance(m, dict) or m.get("kind") != "run":
            raise SpmcError(f"{path}: not a run directory made by 'spmc run'")
        return cls(path)

    def __repr__(self) -> str:
        return f"Run({str(self.path)!r})"

    def _table(self, name: str) -> pd.DataFrame:
        ex = _export()
        try:
            return ex.read_table(self.path, name)
        except ex.ExportError as exc:
            raise SpmcError(str(exc)) from None

    @functools.cached_property
    def trials(self) -> pd.DataFrame:
        """One row per trial x filter: window-mean and final errors, divergence, NEES/NIS means."""
        return self._table("trials")

    @functools.cached_property
    def timeseries(self) -> pd.DataFrame:
        """Per trial, filter and step: the errors, NEES, NIS, iterations (if the run kept a time series)."""
        return self._table("timeseries")

    @functools.cached_property
    def percentiles(self) -> pd.DataFrame:
        """Percentiles of the per-trial mean errors per filter and population (converged / all)."""
        return self._table("percentiles")

    @functools.cached_property
    def timing(self) -> pd.DataFrame:
        """Per-trial compute time."""
        return self._table("timing")

    @functools.cached_property
    def manifest(self) -> dict[str, Any]:
        """``manifest.json``: version, git revision, seed, trials, filters, host, start/end, chunks."""
        return json.loads((self.path / "manifest.json").read_text())

    @property
    def chunks(self) -> pd.DataFrame:
        """The manifest's per-chunk timings (first, last trial, wall_s, jobs, backend)."""
        import pandas as pd

        return pd.DataFrame(self.manifest.get("chunks") or [], columns=["first", "last", "wall_s", "jobs", "backend"])

    @functools.cached_property
    def scenario(self) -> Scenario:
        """The resolved scenario the run was made with (``config.yaml``)."""
        try:
            return engine.load_run_scenario(self.path)
        except (engine.RunError, ValueError) as exc:
            raise SpmcError(str(exc)) from None

    @property
    def n_trials(self) -> int:
        """The number of trials of the run."""
        if self._result is not None:
            return len(set(self._result.trials_columns["trial"].tolist()))
        return int(self.manifest["trials"])

    @property
    def wall_s(self) -> float | None:
        """Wall-clock seconds of the session that returned this object (``None`` for an opened run)."""
        return None if self._result is None else self._result.wall_s

    def summary(self) -> str:
        """The percentile tables per filter, as ``spmc run`` prints them, with the trial counts."""
        if self._result is not None:
            pt, tr = self._result.percentile_columns, self._result.trials_columns
        else:
            pt, tr = tables.columns_of(self.percentiles), tables.columns_of(self.trials)
        start = self.scenario.time.error_window_start_s
        excl = self.scenario.divergence.exclude_inconsistent
        out = []
        for label in dict.fromkeys(pt["filter"].tolist()):
            rows = [i for i, f in enumerate(pt["filter"].tolist()) if f == label]
            n = int(pt["trials"][rows[0]])
            nl = int(pt["lost" if "lost" in pt else "diverged"][rows[0]])  # (runs before issue 33: diverged)
            ni = int(pt["inconsistent"][rows[0]]) if "inconsistent" in pt else 0
            kept = int(pt["trials"][[i for i in rows if pt["population"][i] == "converged"][0]])
            out.append(f"\n{label}: per-trial mean errors over t >= {start:g} s, {kept} of {n} trials (the trials not "
                       f"lost{' nor inconsistent' if excl else ''})")  # fmt: skip
            out.append(f"  lost: {percentiles.rate_text(nl, n, False)}; "
                       f"inconsistent (truth-based flag): {percentiles.rate_text(ni, n, False)}")  # fmt: skip
            out.append(percentiles.format_table(pt, label, "converged"))
            if kept < n:
                out += ["all trials (lost = inf):", percentiles.format_table(pt, label, "all")]
        from ..outputs.summary import remedies, summarize

        cfg = {f.label: f.model_dump() for f in self.scenario.filters}
        for s in summarize(tr, list(dict.fromkeys(pt["filter"].tolist())), {k: v["type"] for k, v in cfg.items()}, excl):
            out += [f"\nwhat to try: {r}" for r in remedies(s, cfg.get(s.label))]
        if "invalid" in tr and tr["invalid"].any():
            bad = len(set(tr["trial"][tr["invalid"].astype(bool)].tolist()))
            out.append(f"\n{bad} trial(s) drew an invalid scenario (counted as lost at step 0; "
                       "column 'invalid', reason 'invalid draw: ...' in trials.parquet)")  # fmt: skip
        return "\n".join(out)

    def rerun(self, trial: int, out: str | Path | None = None) -> Rerun:
        """Recompute ``trial`` alone from its seed; ``identical`` says whether it matches ``trials``.

        ``out``: also keep its time series there (a Parquet file).
        """
        from ..mc import rerun as rr

        ex = _export()
        with tempfile.TemporaryDirectory(prefix="spmc-rerun-") as tmp:
            target = Path(out) if out is not None else Path(tmp) / "timeseries.parquet"
            try:
                res = rr.rerun_trial(self.path, int(trial), target)
            except rr.RerunError as exc:
                raise SpmcError(str(exc)) from None
            ts = ex.read_parquet(target, "timeseries")
        lines = res.lines if out is not None else [ln for ln in res.lines if not ln.startswith("time series -> ")]
        return Rerun(int(trial), res.trials, ts, res.identical, lines)

    def report(self, progress: FigureProgress | None = None, jobs: int | None = None) -> Path:
        """Write ``figures/`` and ``report.html`` from the run's tables; return the report's path (``jobs``:
        processes drawing the figures, default the cores available; the same files for any ``jobs``)."""
        from ..outputs import report as rep

        try:
            with locked(self.path, "spmc report"):
                return rep.build_run_report(self.path, progress, default_jobs() if jobs is None else jobs)
        except rep.ReportError as exc:
            raise SpmcError(exc.lines()) from None
        except RunDirError as exc:
            raise SpmcError(str(exc)) from None

    def export(self, format: str, tables: list[str] | None = None, out: str | Path | None = None,
               overwrite: bool = False) -> list[Path]:  # fmt: skip
        """Write tables as ``csv`` (+ units sidecars), ``mat`` (MATLAB structs) or ``parquet``; see :func:`export`."""
        return export(self.path, format, tables, out, overwrite)


def default_jobs() -> int:
    """The default of ``jobs``: the cores available to this process (affinity mask and cgroup quota)."""
    from ..mc.cores import available_cores

    return available_cores()


def _options(jobs: int | None, chunk_size: int | None, backend: str, kernels: str | None, scheduler: str | None,
             say: Callable[[str], None] | None, command: list[str] | None, **kw: Any) -> engine.RunOptions:  # fmt: skip
    jobs = default_jobs() if jobs is None else jobs
    if scheduler is not None and backend not in ("auto", "dask"):
        raise SpmcError(f"--scheduler is a Dask scheduler's address: it needs --backend dask, not --backend {backend}")
    backend = "dask" if scheduler is not None else backend
    if backend not in BACKENDS:
        raise SpmcError(f"--backend must be auto, fork, threading, loky or dask (got {backend!r})")
    if kernels not in (None, *KERNELS):
        raise SpmcError(f"--kernels must be numpy or compiled (got {kernels!r})")
    return engine.RunOptions(jobs=jobs, chunk_size=chunk_size, backend=backend, kernels=kernels, scheduler=scheduler,
                             say=say, command=list(sys.argv) if command is None else list(command), **kw)  # fmt: skip


def _start(scn: Scenario, out: Path, opts: engine.RunOptions, progress: Progress | None, report: bool) -> Run:
    try:
        res = engine.run(scn, out, opts, progress)
    except (engine.RunError, RunDirError) as exc:
        raise SpmcError(str(exc)) from None
    r = Run(out, res)
    if report:
        r.report(jobs=opts.jobs)
    return r


def run(scenario: Scenario | str | Path | Mapping[str, Any], *, trials: int | None = None,
        out: str | Path | None = None, seed: int | None = None, jobs: int | None = None, chunk_size: int | None = None,
        backend: str = "auto", kernels: str | None = None, scheduler: str | None = None, timeseries: str = "full",
        overwrite: bool = False, report: bool = False, progress: Progress | None = None,
        say: Callable[[str], None] | None = None, command: list[str] | None = None) -> Run:  # fmt: skip
    """Run a Monte Carlo campaign (every filter of the scenario on every trial) into ``out``.

    ``scenario``: a :class:`Scenario`, a YAML file or a scenario mapping. ``out`` defaults to
    ``runs/<scenario name>``; an existing non-empty directory needs ``overwrite=True``. The
    options are those of ``spmc run`` (``jobs``: default the cores available; ``kernels``: default
    ``compiled``, the Numba kernels, ``numpy`` the readable reference; ``timeseries``: ``none``,
    ``summary`` or ``full``); ``report=True`` also writes the figures and report.html.
    ``progress(done, total, diverged_per_filter)`` is called about every 0.5 s (trials done, from the
    chunks' trial-steps) and as chunks finish; ``say`` gets notes.
    Raises :class:`SpmcError` for bad input; results do not depend on ``jobs``, ``chunk_size`` or ``backend``.
    """
    scn = as_scenario(scenario)
    out = Path(out) if out is not None else Path("runs") / scn.name
    opts = _options(jobs, chunk_size, backend, kernels, scheduler, say, command, trials=trials, seed=seed,
                    timeseries=timeseries, overwrite=overwrite)  # fmt: skip
    return _start(scn, out, opts, progress, report)


def resume(path: str | Path, *, trials: int | None = None, seed: int | None = None, jobs: int | None = None,
           chunk_size: int | None = None,
           backend: str = "auto", kernels: str | None = None, scheduler: str | None = None,
           timeseries: str | None = None, report: bool = False, progress: Progress | None = None,
           say: Callable[[str], None] | None = None, command: list[str] | None = None) -> Run:  # fmt: skip
    """Finish (or, with a larger ``trials``, extend) the run in ``path`` from its finished chunks.

    The run keeps its scenario, seed, time-series mode and (unless ``kernels`` is given) its kernels;
    a ``seed`` or ``timeseries`` other than the run's is an error.
    """
    path = Path(path)
    try:
        scn = engine.load_run_scenario(path)
        timeseries = timeseries or engine.recorded_timeseries(path)
    except (engine.RunError, ValueError) as exc:
        raise SpmcError(str(exc)) from None
    opts = _options(jobs, chunk_size, backend, kernels, scheduler, say, command, trials=trials, seed=seed,
                    timeseries=timeseries, resume=True)  # fmt: skip
    return _start(scn, path, opts, progress, report)


def export(run_dir: str | Path, format: str, tables: list[str] | None = None, out: str | Path | None = None,
           overwrite: bool = False) -> list[Path]:  # fmt: skip
    """Export a run's tables (default: all it has; some of ``trials``, ``timeseries``, ``percentiles``,
    ``timing``) as ``csv`` (a ``<table>.units.csv`` sidecar each), ``mat`` (one ``<run>.mat``, a struct per
    table with ``units``) or ``parquet`` into ``out`` (default ``<run>/export``).

    Each file is written atomically; an existing destination is refused unless ``overwrite``.
    Returns the files written.
    """
    ex = _export()
    try:
        return ex.export_run(Path(run_dir), format, tables, None if out is None else Path(out), overwrite)
    except ex.ExportError as exc:
        raise SpmcError(str(exc)) from None


@dataclass
class ReportOutcome:
    """What :func:`report` wrote, and the problems of the paths it could not report on."""

    written: list[Path] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)


def report(paths: str | Path | list[str | Path], progress_of: Callable[[Path], ContextManager] | None = None,
           jobs: int | None = None) -> ReportOutcome:  # fmt: skip
    """Reports for run directories, folders of runs (each run's report and an ``index.html``) and sweeps.

    ``paths``: one path, or a list of them. ``jobs``: processes drawing the figures (default the cores available;
    the same files for any ``jobs``).
    ``progress_of(run_dir)``: a context manager giving a figure-progress callback (or None) per run.
    A broken run is listed in ``problems`` and the others are still reported.
    """
    from ..outputs import report as rep
    from ..outputs.sweep_report import build_sweep_report
    from ..studies.sweep import SweepError

    jobs = default_jobs() if jobs is None else jobs
    res = ReportOutcome()
    for p in map(Path, [paths] if isinstance(paths, (str, Path)) else paths):
        if (p / "sweep.json").is_file():  # a sweep: its own report, the points' reports and an index
            try:
                res.written.append(build_sweep_report(p, jobs))
            except (SweepError, rep.ReportError) as exc:
                res.problems += exc.lines() if isinstance(exc, rep.ReportError) else [str(exc)]
            continue
        try:
            runs, is_folder = rep.discover(p)
        except rep.ReportError as exc:
            res.problems += exc.lines()
            continue
        good: list[Path] = []
        failed: dict[Path, list[str]] = {}
        for r in runs:
            try:
                with (progress_of(r) if progress_of else nullcontext()) as prog:
                    res.written.append(Run(r).report(prog, jobs))
                good.append(r)
            except SpmcError as exc:
                res.problems += exc.lines
                failed[r] = [line.removeprefix(f"{r}: ") for line in exc.lines]
        if is_folder:
            res.written.append(rep.build_index(p, good, failed))
    return res
