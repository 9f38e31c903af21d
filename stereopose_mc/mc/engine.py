"""The Monte Carlo engine: chunks of trials -> joblib (loky/threading) or Dask -> files.

A run directory holds (see docs/outputs.md):

- ``config.yaml`` (the resolved scenario) and ``manifest.json`` (version, git revision,
  root seed, trial count, filters, host, start/end, scenario hash, per-chunk timings);
- ``chunks/``: one ``trials-<first>-<last>.parquet`` (+ ``timeseries-...``, ``timing-...``)
  per finished chunk, each written atomically (temporary name, then rename) as soon as
  the chunk finishes (by the thread that computed it, or by the driver for chunks from
  worker processes), so a run killed at any moment loses at most the chunks in flight;
- after all chunks: ``trials.parquet``, ``timeseries.parquet``, ``timing.parquet`` and
  the percentile tables, merged in trial order into a staging directory and published
  once every chunk verifies (``rundir/publish.py``). The time series is merged while the
  chunks run (``rundir/merge.py``): this session's chunks from memory as their
  predecessors are in, earlier sessions' chunks from their files.

Determinism: trial ``j`` draws only from the ``j``-th ``SeedSequence`` child of the root
seed, and every kernel treats the trials of a chunk independently, so the merged
tables are the same bytes for any ``--jobs``, ``--chunk-size``, backend or resume.
Wall-clock timings are kept out of ``trials.parquet`` (they are in ``timing.parquet``
and the manifest) for that reason.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterable, Mapping

import numpy as np
import yaml
from threadpoolctl import threadpool_info, threadpool_limits

from typing import NamedTuple

from ..config.budget import memory_problem
from ..config.resolve import FilterSetup, Setup, filter_setup_of, setup_of
from ..config.dispersions import units as dispersion_units
from ..config.schema import SCHEMA_VERSION, Scenario
from ..config.sensor import feature_count
from ..core.layout import n_state
from ..rundir import integrity, publish, runlock, store, tables
from ..rundir.merge import InOrderMerge
from ..rundir.percentiles import percentile_columns, percentiles_markdown
from ..sim import measurements as meas
from ..sim.truth import Truth
from ..sim.truth_cache import cached_truth
from . import dispersed, forked, rows, scheduler_probe, startup
from .progress import PROXY_EVERY_S, SharedSteps, StepCounter, Ticker
from .trial import Bounds, run_chunk

if TYPE_CHECKING:  # pandas is not imported by a run (~0.25 s): only by RunResult.trials / .percentiles
    import pandas as pd
    import pyarrow as pa

TIMESERIES_MODES = ("none", "summary", "full")
DEFAULT_KERNELS = "compiled"  # the Numba kernels; "numpy" is the readable reference (docs/performance.md)
SUMMARY_TRIALS = 100  # trials kept in timeseries.parquet with --timeseries summary


class RunError(Exception):
    """A run that cannot start or resume as asked (bad directory, changed scenario...)."""


def scenario_hash(scn: Scenario) -> str:
    """SHA-256 of the scenario's canonical JSON, without the trial count."""
    d = scn.model_dump(mode="json")
    d.pop("trials", None)
    if d.get("dispersions") is None:  # scenarios without dispersions keep their hash
        d.pop("dispersions", None)
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()


class Prepared(NamedTuple):
    """What every chunk of a scenario shares: SI setup, truth, exact measurements, filters."""

    scenario: Scenario
    setup: Setup
    truth: Truth
    exact: meas.Measurements
    filters: list[FilterSetup]
    bounds: Bounds


def prepare(scn: Scenario) -> Prepared:
    """Resolve a scenario and compute its (trial-independent) truth and exact measurements.

    The truth comes from the on-disk truth cache when it has it (``sim/truth_cache.py``:
    the same bits; ``SPMC_NO_CACHE=1`` turns it off).
    """
    setup = setup_of(scn)
    try:
        truth = cached_truth(setup)
    except RuntimeError as exc:  # an integration that hit its limit
        raise RunError(f"{scn.name}: the true trajectory cannot be integrated ({exc}); check orbit, "
                       "initial_state and truth_model") from None  # fmt: skip
    if scn.measurements.source == "tracks":  # the truth file's states, or none (mc/tracked.py)
        from ..sim import tracks_file  # pandas: only runs measured by tracks import it
        from . import tracked

        try:
            truth = tracked.file_truth(scn, setup, truth)
            tracked.file_tracks(scn, setup)  # read and checked once, before any chunk
        except tracks_file.TracksFileError as exc:
            raise RunError(str(exc)) from None
        if setup.pseudo and scn.measurements.tracks.truth_file is None and setup.alpha_method == "truth_plus_noise":
            raise RunError(f"{scn.name}: measurements.inertia_pseudo_measurement needs the true angular acceleration "
                           "(measurements.tracks.truth_file) or a differentiated angular_acceleration_source "
                           "(docs/angular-acceleration.md)")  # fmt: skip
    exact = meas.noise_free(setup, truth)
    filters = [filter_setup_of(f, setup) for f in scn.filters]
    d = scn.divergence
    bounds = Bounds(d.rho_m, d.rho_dot_mps, d.omega_degps, d.k, d.nis_ratio, d.nis_window_steps, d.nis_start_s,
                    d.gated_fraction, d.sigma_ratio, d.nees_factor)  # fmt: skip
    return Prepared(scn, setup, truth, exact, filters, bounds)


@functools.lru_cache(maxsize=4)
def _prepared(scenario_json: str) -> Prepared:
    """``prepare`` computed once per process and scenario (chunks of a run share it)."""
    return prepare(Scenario.model_validate_json(scenario_json))


@dataclass
class ChunkOutput:
    trials: np.ndarray
    trials_table: pa.Table
    timeseries_table: pa.Table | None
    timing_table: pa.Table
    wall_s: float
    diverged: int
    diverged_by: dict[str, int] = field(default_factory=dict)  # per filter
    tracks_table: pa.Table | None = None  # measurements.source images | tracks: the chunk's tracks (and audit)


_PREPARE_LOCK = threading.Lock()  # threads of one process share prepare()'s cache: compute it once


def compute_chunk(scenario_json: str, trials: np.ndarray, timeseries: str, kernels: str = DEFAULT_KERNELS,
                  tick: Callable[[int], None] | None = None) -> ChunkOutput:  # fmt: skip
    """Run one chunk of trials (any process): pure function of its arguments (``tick``: progress only).

    BLAS runs single-threaded here: a multithreaded BLAS splits a product or a solve
    differently with the thread count, which changes the last bits of the results.
    Parallelism comes from the chunks instead.
    """
    with threadpool_limits(limits=1):
        with _PREPARE_LOCK:
            scn, setup, truth, exact, filters, bounds = _prepared(scenario_json)
        tracks = None
        if scn.measurements.source == "images" and dispersed.has_dispersions(scn):  # per-trial renders and tracks
            parts: list = []
            res, disp = dispersed.run_chunk(scn, np.asarray(trials), setup, bounds, kernels, tick, parts)
            if parts:
                import pandas as pd

                tracks = pd.concat(parts, ignore_index=True).sort_values(["trial", "step", "track_id"], kind="stable")
        elif scn.measurements.source != "model":  # tracks fill the filters' feature slots
            from . import tracked  # pandas, OpenCV: only runs measured by tracks import them

            images = scn.measurements.source == "images"  # progress: the tracking's, not the filters'
            tracks = tracked.tracks_for(scn, setup, truth, np.asarray(trials), tick)
            res, disp = tracked.run_chunk(scn, np.asarray(trials), setup, truth, exact, filters, bounds, tracks,
                                          kernels, None if images else tick), None  # fmt: skip
        elif dispersed.has_dispersions(scn):
            res, disp = dispersed.run_chunk(scn, np.asarray(trials), setup, bounds, kernels, tick)
        else:
            res, disp = run_chunk(scn.seed, np.asarray(trials), setup, truth, exact, filters, bounds, kernels,
                                  tick), None  # fmt: skip
    tc = rows.trials_columns(res, truth.t, setup.window_start, scn.seed)
    if disp is not None:
        tc = dispersed.with_columns(tc, disp)
    ts = None
    if timeseries != "none":
        keep = None if timeseries == "full" else (np.asarray(trials) < SUMMARY_TRIALS)
        ts = rows.timeseries_columns(res, truth.t, keep)
        if ts is not None:  # filter-major blocks -> (trial, filter in scenario order, step), as in the merged file
            ts = tables.arrow_table(tables.take_rows(ts, np.argsort(ts["trial"], kind="stable")))
    first = int(np.min(trials))
    timing = tables.arrow_table(rows.timing_columns(res, first))
    by = {label: int(tc["diverged"][tc["filter"] == label].sum()) for label in dict.fromkeys(tc["filter"].tolist())}
    tt = None if tracks is None else tables.arrow_table(tables.columns_of(tracks))
    return ChunkOutput(np.asarray(trials), tables.arrow_table(tc), ts, timing, res.runtime_s,
                       int(tc["diverged"].sum()), by, tt)  # fmt: skip


def plan_chunks(todo: np.ndarray, chunk_size: int) -> list[np.ndarray]:
    """Split sorted trial indices into contiguous runs of at most ``chunk_size``."""
    todo = np.sort(np.asarray(todo, dtype=np.int64))
    if todo.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(todo) != 1) + 1
    out = []
    for run in np.split(todo, breaks):
        out.extend(run[i : i + chunk_size] for i in range(0, run.size, chunk_size))
    return out


def _chunk_name(kind: str, trials: np.ndarray) -> str:
    return f"{kind}-{int(trials[0]):07d}-{int(trials[-1]):07d}.parquet"


@dataclass
class RunOptions:
    trials: int | None = None
    seed: int | None = None
    jobs: int = 1
    chunk_size: int | None = None  # None: auto_chunk_size
    backend: str = "auto"  # threads for --kernels compiled (nogil kernels), else loky
    kernels: str | None = "compiled"  # compiled | numpy (mc.trial.step_functions); None: compiled, or a resumed run's
    scheduler: str | None = None
    timeseries: str = "full"
    overwrite: bool = False
    resume: bool = False
    command: list[str] = field(default_factory=lambda: list(sys.argv))
    say: Callable[[str], None] | None = None  # notes for the user (rejected chunks, applied options)


@dataclass
class RunResult:
    """A finished run: its directory, merged trials table and percentile table (as :data:`tables.Columns`)."""

    out: Path
    trials_columns: tables.Columns
    percentile_columns: tables.Columns
    wall_s: float
    chunks_run: int

    @functools.cached_property
    def trials(self) -> pd.DataFrame:
        """``trials.parquet`` as a DataFrame (what ``pd.read_parquet`` gives)."""
        return tables.arrow_table(self.trials_columns).to_pandas()

    @functools.cached_property
    def percentiles(self) -> pd.DataFrame:
        """``percentiles.parquet`` as a DataFrame."""
        return tables.arrow_table(self.percentile_columns).to_pandas()


Progress = Callable[[int, int, dict], None]  # (trials done, total, diverged so far per filter)


def _parquet_meta(scn: Scenario, shash: str, kind: str) -> dict[str, str]:
    return {"stereopose_mc.schema_version": str(SCHEMA_VERSION), "stereopose_mc.table": kind,
            "stereopose_mc.scenario": scn.name, "stereopose_mc.scenario_hash": shash,
            "stereopose_mc.seed": str(scn.seed), "stereopose_mc.units": "per field: metadata key 'unit'"}  # fmt: skip


def _write_table(path: Path, table: pa.Table | tables.Columns, meta: dict[str, str]) -> dict:
    """A run table as Parquet, atomically, with the run's metadata and every column's unit; the file's record
    (``store.write_parquet``)."""
    return store.write_parquet(path, table, meta, units=tables.COLUMN_UNITS)


def _write_chunk(chunk_dir: Path, out: ChunkOutput, meta: dict[str, str], spec: integrity.RunSpec) -> None:
    # the sidecar (identity, range, rows, checksums) is the chunk's commit marker: written last
    first, last = int(out.trials[0]), int(out.trials[-1])
    meta = {**meta, "stereopose_mc.run_id": spec.run_id, "stereopose_mc.first": str(first),
            "stereopose_mc.last": str(last)}  # fmt: skip
    tabs = {"timeseries": out.timeseries_table if _timeseries_rows(out) is not None else None,
            "tracks": out.tracks_table, "timing": out.timing_table, "trials": out.trials_table}  # fmt: skip
    written = {}  # the files' checksums, taken as they are written (not read back for the sidecar)
    for kind, table in tabs.items():
        if table is not None:
            name = _chunk_name(kind, out.trials)
            written[name] = _write_table(chunk_dir / name, table, meta)
    integrity.write_sidecar(chunk_dir, spec, first, last, out.diverged_by, written)


_WATCHING: list[int] = []  # the driver pid this worker process already watches


def _die_with(driver_pid: int) -> None:
    """In a worker process: exit as soon as the driver is gone (killed, even by SIGKILL).

    A daemon thread polls every 0.5 s whether the worker was re-parented or the driver's
    pid vanished; orphaned workers would otherwise finish their chunks (minutes) for nobody.
    """
    if _WATCHING or os.getpid() == driver_pid:
        return
    _WATCHING.append(driver_pid)
    ppid = os.getppid()

    def watch() -> None:
        while True:
            time.sleep(0.5)
            try:
                os.kill(driver_pid, 0)
            except ProcessLookupError:
                os._exit(1)
            except OSError:
                pass
            if os.getppid() != ppid:
                os._exit(1)

    threading.Thread(target=watch, name="spmc-parent-watch", daemon=True).start()


def compute_chunk_in_worker(driver_pid: int | None, scenario_json: str, trials: np.ndarray, timeseries: str,
                            kernels: str = DEFAULT_KERNELS, steps: Mapping | None = None):  # fmt: skip
    """:func:`compute_chunk` in a local worker process that dies with the driver ``driver_pid``
    (``steps``: the driver's :class:`StepCounter` mapping, a Manager proxy)."""
    if driver_pid is not None:
        _die_with(driver_pid)
    tick = None if steps is None else StepCounter.tick_of(steps, int(trials[0]), PROXY_EVERY_S)
    try:
        return compute_chunk(scenario_json, trials, timeseries, kernels, tick)
    finally:
        if tick is not None:
            tick.flush()


AUTO_CHUNK_MAX = 250  # compiled kernels: trials per chunk at most (memory ~ chunk x steps x n^2)
AUTO_CHUNK_MIN = 32  # compiled kernels: trials per chunk at least, at a state of AUTO_CHUNK_MIN_N (min_chunk)
AUTO_CHUNK_MIN_N = 30  # case B's state (5 features), where AUTO_CHUNK_MIN was measured


def min_chunk(n: int) -> int:
    """The fewest trials worth a chunk (a thread) of their own, for a state of length ``n``.

    ``AUTO_CHUNK_MIN`` at ``AUTO_CHUNK_MIN_N`` (case B: below it the per-step Python work, which holds the GIL,
    outweighs the kernels' time, and two threads take longer than one; measured: 2-16 trials of case B, 0.1-0.4 s
    more with 2 threads than inline, 30 trials in chunks of 15 ~0.25 s more), fewer for larger states in proportion
    to ``(AUTO_CHUNK_MIN_N / n)^2`` (a trial-step's kernels grow as ``n^2`` to ``n^3``, its Python work hardly:
    configs/mission-realistic.yaml, ``n = 87``, 30 trials of ``spmc run``: 4.2-5.0 s inline, 3.4-3.8 s in two chunks
    on two threads), and at least 2.
    """
    return max(2, math.ceil(AUTO_CHUNK_MIN * (AUTO_CHUNK_MIN_N / max(n, 1)) ** 2))


def auto_chunk_size(opts: RunOptions, n_trials: int, n: int = AUTO_CHUNK_MIN_N) -> int:
    """The chunk size when ``--chunk-size`` is not given (``n``: the scenario's state length).

    numpy kernels: 50 (as before). Compiled kernels: the trials split evenly over the
    jobs, at most ``AUTO_CHUNK_MAX``: the per-step Python work and the per-chunk tables
    and files (which hold the GIL) are then paid as few times as possible; and at least
    ``min_chunk(n)`` (or all the trials, if fewer). A run of one chunk runs inline
    (``local_backend``). Results do not depend on the chunk size.
    """
    if opts.kernels != "compiled":
        return 50
    share = -(-n_trials // max(1, opts.jobs))
    return int(max(1, min(AUTO_CHUNK_MAX, max(share, min(n_trials, min_chunk(n))))))


def state_length(scn: Scenario) -> int:
    """The length of the filters' state in ``scn`` (its features, or its feature slots)."""
    return n_state(feature_count(scn))


def compute_chunks(scn: Scenario, trials: np.ndarray, opts: RunOptions) -> list[ChunkOutput]:
    """The trials ``trials`` of ``scn`` as a run computes them (its chunks, ``opts.jobs`` threads or processes as
    ``local_backend`` picks them), in the order of ``trials``; nothing written, no progress (a study's evaluations:
    ``studies.tuning``). The same results for any ``jobs``, chunk size or backend."""
    todo = np.asarray(trials, dtype=np.int64)
    chunks = plan_chunks(todo, opts.chunk_size or auto_chunk_size(opts, todo.size, state_length(scn)))
    outs = list(_iterate(scn.model_dump_json(), chunks, opts, evaluations=True))
    return sorted(outs, key=lambda co: int(co.trials[0]))


def local_backend(opts: RunOptions, n_chunks: int, images: bool = False, evaluations: bool = False) -> str:
    """Where the chunks run: ``inline`` (this thread), ``fork``, ``threading``, ``loky`` or ``dask``.

    One job or one chunk runs inline (no pool to start); ``auto`` picks, for the compiled
    kernels, workers forked from this process on Linux (``mc/forked.py``: nothing imported
    again, and nothing shared, where threads share OpenBLAS's buffer pool), else threads (the
    kernels release the GIL, and a thread imports nothing); and loky processes for the numpy
    kernels (numpy's small-array calls hold the GIL) and for ``images`` campaigns (the
    tracker's Python and numpy work holds it). ``fork`` where it is not available: :class:`RunError`.
    ``evaluations``: a study's many short computations in this process (:func:`compute_chunks`), which
    ``auto`` gives threads: they load the kernels once, forked workers at every evaluation (~0.2 s).
    """
    if opts.backend == "dask":
        return "dask"
    if opts.backend == "fork" and not forked.available():
        raise RunError(f"--backend fork: worker processes are forked on Linux only (this is {sys.platform}); "
                       "use --backend threading or loky")  # fmt: skip
    if opts.jobs == 1 or n_chunks <= 1:
        return "inline"
    if opts.backend == "auto":
        if opts.kernels == "compiled" and not images:
            return "fork" if forked.available() and not evaluations else "threading"
        return "loky"
    return opts.backend


def connect_dask(address: str | None, jobs: int, info: dict | None = None):
    """A Dask client (and its LocalCluster when ``address`` is None); ``info`` gets address and workers."""
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:  # pragma: no cover - depends on the optional extra
        raise RunError("--backend dask needs the optional extra: pip install 'stereopose_mc[dask]'") from None
    cluster = None
    if address:
        try:
            scheduler_probe.probe(address, DASK_CONNECT_TIMEOUT_S)  # a service that is not Dask: hang or 3 EiB
        except scheduler_probe.NotAScheduler as exc:
            raise RunError(f"--scheduler {address}: {exc}") from None
        try:
            client = Client(address, timeout=DASK_CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError, ValueError) as exc:
            raise RunError(f"--scheduler {address}: cannot connect to a Dask scheduler there within "
                           f"{DASK_CONNECT_TIMEOUT_S} s ({type(exc).__name__}: {exc})") from None  # fmt: skip
    else:
        cluster = LocalCluster(n_workers=max(1, jobs), threads_per_worker=1, processes=True,
                               dashboard_address=None)  # fmt: skip
        client = Client(cluster)
    if info is not None:
        info.update(address=client.scheduler.address, workers=len(client.scheduler_info().get("workers", {})))
    return client, cluster


DASK_CONNECT_TIMEOUT_S = 10


def _computed_and_written(write: Callable[[ChunkOutput], None] | None, scenario_json: str, trials: np.ndarray,
                          timeseries: str, kernels: str,
                          tick: Callable[[int], None] | None) -> ChunkOutput:  # fmt: skip
    """:func:`compute_chunk`, then ``write`` of its output, in the calling thread."""
    return _written(write, compute_chunk(scenario_json, trials, timeseries, kernels, tick))


def _threaded(scenario_json: str, chunks: list[np.ndarray], opts: RunOptions, counter: StepCounter | None = None,
              write: Callable[[ChunkOutput], None] | None = None) -> Iterable[ChunkOutput]:  # fmt: skip
    """Chunk outputs as they finish, from ``opts.jobs`` threads of this process (the nogil compiled kernels).

    The standard library's thread pool (joblib's threading backend costs ~0.06 s of imports, paid
    by every run). One BLAS limit for all threads (per-thread limits would undo each other). The
    thread that computed a chunk also writes it (``write``: Parquet encoding and checksums release
    the GIL), so the consumer's thread stays free. When the consumer stops early (an error,
    Ctrl-C), chunks not yet started are cancelled and the running ones are waited for (a thread
    cannot be killed; they still write their files, which a resume keeps).
    """
    from concurrent.futures import ThreadPoolExecutor, as_completed

    with threadpool_limits(limits=1):
        pool = ThreadPoolExecutor(max_workers=opts.jobs, thread_name_prefix="spmc-chunk")
        try:
            futures = [pool.submit(_computed_and_written, write, scenario_json, c, opts.timeseries, opts.kernels,
                                   None if counter is None else StepCounter.tick_of(counter.steps, int(c[0])))
                       for c in chunks]  # fmt: skip
            for f in as_completed(futures):
                yield f.result()
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


def _forked(scenario_json: str, chunks: list[np.ndarray], opts: RunOptions,
            counter: Callable[[Mapping | None], StepCounter] | None = None,
            write: Callable[[ChunkOutput], None] | None = None) -> Iterable[ChunkOutput]:  # fmt: skip
    """Chunk outputs as they finish, from ``opts.jobs`` workers forked from this process (``mc/forked.py``).

    Each worker computes and writes its chunks (``write``, inherited through the fork) and dies with
    this process (``forked``'s ``prctl``, and :func:`_die_with`'s watch as loky's workers have it); progress comes through a :class:`progress.SharedSteps` made before the fork. A
    worker that dies is a :class:`RunError` naming the chunks in flight (the finished chunks are kept).
    """
    steps = None
    if counter is not None:
        labels = [f.label for f in Scenario.model_validate_json(scenario_json).filters]
        steps = counter(SharedSteps([int(c[0]) for c in chunks], labels)).steps

    def job(i: int) -> ChunkOutput:
        c = chunks[i]
        tick = None if steps is None else StepCounter.tick_of(steps, int(c[0]))
        return _computed_and_written(write, scenario_json, c, opts.timeseries, opts.kernels, tick)

    names = [f"trials {int(c[0])}-{int(c[-1])}" for c in chunks]
    try:
        yield from forked.outputs(job, len(chunks), opts.jobs, functools.partial(_die_with, os.getpid()), names)
    except forked.WorkerDied as exc:
        raise RunError(f"{exc}; the finished chunks are kept: continue with spmc run --resume DIR") from None


def _iterate(scenario_json: str, chunks: list[np.ndarray], opts: RunOptions, info: dict | None = None,
             counter: Callable[[Mapping | None], StepCounter] | None = None,
             write: Callable[[ChunkOutput], None] | None = None,
             evaluations: bool = False) -> Iterable[ChunkOutput]:  # fmt: skip
    """Chunk outputs as they finish, in any order (``info``: where they run, for the manifest;
    ``evaluations``: :func:`local_backend`'s).

    ``counter(steps)``: called once with the mapping the chunks will count their trial-steps in
    (None: a plain dict, for this process's threads; a :class:`SharedSteps` for forked workers; a
    Manager's dict for loky processes); Dask's remote chunks are counted when they end.
    ``write(chunk)``: done to every chunk before it is yielded: in the thread or forked worker that
    computed it (inline, threading, fork), else in this one as it arrives.
    """
    images = json.loads(scenario_json)["measurements"].get("source") == "images"
    where = local_backend(opts, len(chunks), images, evaluations)
    if info is not None:
        info["ran_as"] = where
    if where == "fork":
        yield from _forked(scenario_json, chunks, opts, counter, write)
        return
    if where in ("inline", "threading"):
        sc = None if counter is None else counter(None)
        if where == "threading":
            yield from _threaded(scenario_json, chunks, opts, sc, write)
            return
        for c in chunks:
            yield _computed_and_written(write, scenario_json, c, opts.timeseries, opts.kernels,
                                        None if sc is None else StepCounter.tick_of(sc.steps, int(c[0])))  # fmt: skip
        return
    from joblib import Parallel, delayed, parallel_config

    driver = None if opts.scheduler else os.getpid()  # remote workers outlive us by design
    manager = None
    if where != "dask" and counter is not None:
        from multiprocessing import Manager

        manager = Manager()  # a server process; no files
        steps = counter(manager.dict()).steps
    else:
        steps = None
    calls = (delayed(compute_chunk_in_worker)(driver, scenario_json, c, opts.timeseries, opts.kernels, steps)
             for c in chunks)  # fmt: skip
    written = functools.partial(_written, write)
    if where == "dask":
        from dask.distributed import KilledWorker

        client, cluster = connect_dask(opts.scheduler, opts.jobs, info)
        try:
            with parallel_config(backend="dask"):
                yield from map(written, Parallel(return_as="generator_unordered")(calls))
        except (KilledWorker, OSError) as exc:  # a chunk that kept killing workers, a lost scheduler
            raise RunError(f"Dask backend failed ({type(exc).__name__}: {exc}); the finished chunks are kept: "
                           "continue with spmc run --resume DIR (see docs/distributed.md)") from None  # fmt: skip
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
        return
    try:
        with parallel_config(backend=where, n_jobs=opts.jobs):
            yield from map(written, Parallel(return_as="generator_unordered")(calls))
    finally:
        if manager is not None:
            manager.shutdown()


def _written(write: Callable[[ChunkOutput], None] | None, co: ChunkOutput) -> ChunkOutput:
    if write is not None:
        write(co)
    return co


def _merged(files: list[Path], order: dict[str, int]) -> tables.Columns:
    """Chunk files' rows, concatenated and sorted by (trial, filter in the scenario's order), stably."""
    import pyarrow.parquet as pq

    cols = tables.concat_columns([tables.columns_of(pq.ParquetFile(f).read()) for f in files])  # read_table imports pandas
    rank = np.array([order[f] for f in cols["filter"].tolist()], dtype=np.int64)
    return tables.take_rows(cols, np.lexsort((rank, cols["trial"])))


def finalize(out: Path, scn: Scenario, shash: str, filter_order: list[str], spec: integrity.RunSpec | None = None,
             dest: Path | None = None,
             timeseries: InOrderMerge | None = None) -> tuple[tables.Columns, tables.Columns]:  # fmt: skip
    """Merge chunk files into the run's tables and write the percentile tables into ``dest``
    (default ``out``; a run stages them and publishes them together: ``rundir/publish.py``).

    ``timeseries``: the run's time-series merge (:func:`timeseries_merge`, fed as the chunks
    finished; None: no time series), closed here. With ``spec``, the merged tables are checked
    (exactly one row per trial x filter, the full time series when it is on):
    :class:`integrity.IntegrityError`. Returns the merged trials table and the percentile table.
    """
    order = {name: i for i, name in enumerate(filter_order)}
    trials = _merged(sorted((out / "chunks").glob("trials-*.parquet")), order)
    chunk_dir, out = out / "chunks", (out if dest is None else dest)
    if spec is not None:
        integrity.check_trials_table(trials, spec)
    store.write_parquet(out / "trials.parquet", trials, _parquet_meta(scn, shash, "trials"),
                        units={**tables.COLUMN_UNITS, **dispersion_units(scn)})
    files = sorted(chunk_dir.glob("timing-*.parquet"))
    if files:
        _write_table(out / "timing.parquet", _merged(files, order), _parquet_meta(scn, shash, "timing"))
    if timeseries is not None:
        n_ts = timeseries.close()
        if spec is not None and n_ts != spec.rows("timeseries", 0, spec.trials - 1):
            raise integrity.IntegrityError([f"{timeseries.stream.path}: {n_ts} rows, not the full time series"])
    files = sorted(chunk_dir.glob("tracks-*.parquet"))  # measurements.source images | tracks
    if files:
        store.write_parquet_stream(out / "tracks.parquet", files, _parquet_meta(scn, shash, "tracks"),
                                   units=tables.COLUMN_UNITS)  # fmt: skip
    excl = scn.divergence.exclude_inconsistent
    pt = percentile_columns(trials, list(scn.percentiles), excl)
    store.atomic_write_text(out / "percentiles.csv", tables.csv_text(pt))
    _write_table(out / "percentiles.parquet", pt, _parquet_meta(scn, shash, "percentiles"))
    store.atomic_write_text(out / "percentiles.md", f"# {scn.name}: percentiles of per-trial mean errors\n\n"
                            + percentiles_markdown(pt, trials, excl))  # fmt: skip
    return trials, pt


def timeseries_merge(path: Path, scn: Scenario, shash: str, keys: Iterable[int]) -> InOrderMerge:
    """The merge of the chunks' time series (keys: their first trials) into ``path``, the run's
    ``timeseries.parquet`` (fixed row groups, metadata and units: the bytes do not depend on the chunking)."""
    meta, units = _parquet_meta(scn, shash, "timeseries"), tables.COLUMN_UNITS
    return InOrderMerge(keys, store.ParquetStream(path, meta, units))


def _timeseries_rows(co: ChunkOutput) -> pa.Table | None:
    """A chunk's time-series table, None when it has no rows (then it has no time-series file)."""
    return co.timeseries_table if co.timeseries_table is not None and co.timeseries_table.num_rows else None


def run_spec(scn: Scenario, shash: str, timeseries: str, code: str | None = None) -> integrity.RunSpec:
    """What every chunk of this run must agree with (identity, trials, filters, steps)."""
    code = integrity.code_version() if code is None else code
    steps = int(round(scn.time.duration_s / scn.time.dt_s)) + 1
    return integrity.RunSpec(integrity.run_id(shash, scn.seed, code), scn.trials, [f.label for f in scn.filters],
                             steps, timeseries)  # fmt: skip


def _say(opts: RunOptions, lines: list[str], limit: int = 20) -> None:
    if opts.say is None:
        return
    for line in lines[:limit]:
        opts.say(line)
    if len(lines) > limit:
        opts.say(f"... and {len(lines) - limit} more")


def _backend_record(opts: RunOptions) -> dict:
    """The manifest's ``backend`` as this session asks for it (``_iterate`` adds ``ran_as`` and Dask's facts)."""
    return {"backend": opts.backend, "jobs": opts.jobs, "address": opts.scheduler, "workers": None,
            "kernels": opts.kernels, "blas": blas_kernels()}  # fmt: skip


def blas_kernels() -> str:
    """The BLAS of this process and the kernels it runs, e.g. ``openblas Haswell`` (OpenBLAS's choice for the CPU,
    or ``OPENBLAS_CORETYPE``'s; their round-off differs). Recorded in the manifest; ``spmc rerun`` says when its own
    differ from the run's."""
    found = {f"{i['internal_api']} {i.get('architecture') or '?'}" for i in threadpool_info() if i["user_api"] == "blas"}
    return ", ".join(sorted(found)) or "none"


def recorded_blas(out: Path) -> str | None:
    """The BLAS kernels a run's last session recorded (``blas_kernels``; None: not recorded)."""
    return (_read_manifest(out).get("backend") or {}).get("blas")


def _new_run_dir(scn: Scenario, out: Path, opts: RunOptions, shash: str, code: str) -> tuple[dict, int]:
    """Create ``out`` complete (config, manifest, chunks/) or not at all, locked; return manifest and lock."""
    manifest = store.base_manifest(opts.command)
    manifest.update(
        kind="run", scenario=scn.name, scenario_hash=shash, seed=scn.seed, trials=scn.trials,
        filters=[f.label for f in scn.filters], state_dim=state_length(scn),
        timeseries=opts.timeseries, code_version=code, start=store.now_iso(),
        end=None, published=None, backend=_backend_record(opts), chunks=[],
    )  # fmt: skip

    def populate(d: Path) -> None:
        (d / "chunks").mkdir()
        store.atomic_write_text(d / "config.yaml", yaml.safe_dump(scn.model_dump(mode="json"), sort_keys=False))
        store.write_json(d / "manifest.json", manifest)

    return manifest, runlock.create_locked(out, opts.overwrite, populate, "spmc run")


def _resume_kernels(out: Path, opts: RunOptions, manifest: dict) -> RunOptions:
    """A resumed run keeps the kernels its chunks ran with (recorded before the first chunk); asking for
    others is refused: the two agree to round-off, not bit for bit (docs/performance.md)."""
    rec = _recorded_kernels(manifest)
    if opts.kernels is None:
        return dataclasses.replace(opts, kernels=rec)
    if opts.kernels != rec:
        raise RunError(f"{out}: this run's chunks run with --kernels {rec}; --kernels {opts.kernels} would mix "
                       "results that agree to round-off only (drop --kernels, or start a new run)")  # fmt: skip
    return opts


def _resume_checks(scn: Scenario, out: Path, opts: RunOptions, manifest: dict, shash: str) -> Scenario:
    """The recorded run's scenario, with a larger ``--trials`` applied; conflicts are errors."""
    recorded = int(manifest["trials"])
    if opts.overwrite:
        raise RunError("--resume and --overwrite conflict: resume keeps the finished chunks")
    if opts.seed is not None and opts.seed != manifest.get("seed"):
        raise RunError(f"{out}: this run was started with seed {manifest.get('seed')}; --seed {opts.seed} "
                       "would need a new run (drop --seed, or start one with --out)")  # fmt: skip
    if manifest.get("scenario_hash") != shash:
        raise RunError(
            f"{out}: the scenario differs from the one this run was started with "
            f"(hash {manifest.get('scenario_hash', '?')[:12]} vs {shash[:12]}); start a new run instead"
        )
    if manifest.get("timeseries") != opts.timeseries:
        raise RunError(f"{out}: this run was started with --timeseries {manifest.get('timeseries')}")
    trials = recorded if opts.trials is None else opts.trials
    if trials < recorded:
        raise RunError(f"{out}: this run has {recorded} trials; --trials {trials} cannot shrink it (start a new run)")
    if trials > recorded and scn.dispersions is not None and scn.dispersions.sampling == "lhs":
        raise RunError(f"{out}: a Latin hypercube depends on the trial count: {recorded} trials cannot be extended to "
                       f"{trials} (start a new run with --trials {trials})")  # fmt: skip
    if trials > recorded:
        _say(opts, [f"{out}: extending the run from {recorded} to {trials} trials (--trials); "
                    f"trials 0-{recorded - 1} are kept"])  # fmt: skip
        manifest["trials"] = trials
    return scn.model_copy(update={"trials": trials})


def run(scn: Scenario, out: Path, opts: RunOptions, progress: Progress | None = None) -> RunResult:
    """Run (or resume) a Monte Carlo campaign into ``out``, holding its lock throughout."""
    t_start = time.perf_counter()
    with startup.paused() as settle:  # the collector off until the start-up is done (mc/startup.py)
        return _run(scn, out, opts, progress, t_start, settle)


def _run(scn: Scenario, out: Path, opts: RunOptions, progress: Progress | None, t_start: float,
         settle: Callable[[], None]) -> RunResult:  # fmt: skip
    if opts.seed is not None and not opts.resume:
        scn = scn.model_copy(update={"seed": opts.seed})
    if opts.trials is not None and not opts.resume:
        scn = scn.model_copy(update={"trials": opts.trials})
    if opts.timeseries not in TIMESERIES_MODES:
        raise RunError(f"--timeseries must be one of {', '.join(TIMESERIES_MODES)}")
    if (opts.chunk_size is not None and opts.chunk_size < 1) or opts.jobs < 1:
        raise RunError("--jobs and --chunk-size must be at least 1")
    if opts.kernels not in (None, "numpy", "compiled"):
        raise RunError(f"--kernels must be numpy or compiled (got {opts.kernels!r})")
    if opts.kernels is None and not opts.resume:
        opts = dataclasses.replace(opts, kernels=DEFAULT_KERNELS)
    too_big = memory_problem(opts.trials or scn.trials, len(scn.filters))
    if too_big:
        raise RunError(f"--trials: {too_big}" if opts.trials else too_big)
    if opts.scheduler and opts.backend != "dask":
        raise RunError("--scheduler needs --backend dask")
    local_backend(opts, 2)  # a backend this machine does not offer (fork off Linux) fails before a file is written
    if opts.scheduler:  # fail before anything is written
        connect_dask(opts.scheduler, opts.jobs)[0].close()
    shash = scenario_hash(scn)
    code = integrity.code_version()
    if not dispersed.has_dispersions(scn):
        _prepared(scn.model_dump_json())  # the shared truth: a scenario that cannot run fails before a file is written
    if opts.resume:
        _read_manifest(out)  # a run directory at all?
        lock = runlock.acquire(out, "spmc run --resume")
    else:
        manifest, lock = _new_run_dir(scn, out, opts, shash, code)
    try:
        if opts.resume:
            manifest = _read_manifest(out)  # as the last writer left it, now that we hold the lock
            opts = _resume_kernels(out, opts, manifest)
            recorded = int(manifest["trials"])
            scn = _resume_checks(scn, out, opts, manifest, shash)
            manifest["code_version"] = code
            manifest.update(end=None, published=None)  # the completion mark, set again once published
            if scn.trials != recorded:
                store.atomic_write_text(out / "config.yaml",
                                        yaml.safe_dump(scn.model_dump(mode="json"), sort_keys=False))  # fmt: skip
            store.write_json(out / "manifest.json", manifest)
        return _run_locked(scn, out, opts, progress, manifest, run_spec(scn, shash, opts.timeseries, code), t_start,
                           settle)  # fmt: skip
    finally:
        runlock.release(lock)


def _run_locked(scn: Scenario, out: Path, opts: RunOptions, progress: Progress | None, manifest: dict,
                spec: integrity.RunSpec, t_start: float, settle: Callable[[], None]) -> RunResult:  # fmt: skip
    chunk_dir = out / "chunks"
    shash = manifest["scenario_hash"]
    integrity.remove_stale_temporaries(chunk_dir)
    v = integrity.verify_chunks(chunk_dir, spec)
    if v.rejected:
        dest = integrity.set_aside(chunk_dir, v.rejected)
        _say(opts, [f"rejected {p}; its trials are recomputed" for p in v.problems]
             + [f"(rejected files moved to {dest})"])  # fmt: skip
    done = np.asarray(v.done_trials(), dtype=np.int64)
    todo = np.setdiff1d(np.arange(scn.trials), done)
    chunks = plan_chunks(todo, opts.chunk_size or auto_chunk_size(opts, todo.size, state_length(scn)))
    scenario_json = scn.model_dump_json()
    meta = _parquet_meta(scn, shash, "chunk")
    n_div = {f: v.diverged().get(f, 0) for f in spec.filters}
    ticker = Ticker(progress, int(done.size), scn.trials, (spec.steps - 1) * len(spec.filters), n_div)
    ticker.report()
    manifest["backend"] = _backend_record(opts)
    store.write_json(out / "manifest.json", manifest)  # kernels and backend before the first chunk
    if opts.kernels == "compiled" and chunks:
        _say(opts, compile_note())  # (imports the kernel modules, and Numba)
    settle()  # the start-up's objects frozen, the collector on for the chunks
    stage = publish.new_stage(out)  # the merged tables are written here; published once all chunks verify
    ts_merge = None
    if spec.timeseries != "none":  # fed as the chunks finish: no read-back of this session's chunk files
        ts_merge = timeseries_merge(stage / "timeseries.parquet", scn, shash, [c["first"] for c in v.chunks]
                                    + [int(c[0]) for c in chunks])  # fmt: skip
    try:
        if ts_merge is not None:  # the chunks of earlier sessions: from their files, at their turn
            for c in v.chunks:
                name = integrity.chunk_file("timeseries", c["first"], c["last"])
                ts_merge.add(c["first"], path=chunk_dir / name if name in c["files"] else None)
        write = functools.partial(_write_chunk, chunk_dir, meta=meta, spec=spec)
        with ticker:
            for co in _iterate(scenario_json, chunks, opts, manifest["backend"], ticker.counter if progress else None,
                               write):  # fmt: skip
                manifest.setdefault("chunks", []).append(
                    {"first": int(co.trials[0]), "last": int(co.trials[-1]), "wall_s": round(co.wall_s, 4),
                     "jobs": opts.jobs, "backend": opts.backend}  # fmt: skip
                )
                store.write_json(out / "manifest.json", manifest)
                if ts_merge is not None:
                    ts = _timeseries_rows(co)
                    path = None if ts is None else chunk_dir / _chunk_name("timeseries", co.trials)
                    ts_merge.add(int(co.trials[0]), ts, path)
                ticker.chunk_done(co.trials.size, co.diverged_by, int(co.trials[0]))
        trials, pt = _verified_and_finalized(chunk_dir, spec, ts_merge,
                                             functools.partial(finalize, out, scn, shash, spec.filters, spec,
                                                               dest=stage, timeseries=ts_merge))  # fmt: skip
    except integrity.IntegrityError as exc:
        _discard(ts_merge, out)
        raise RunError("refusing to merge (nothing published): " + "; ".join(exc.problems)) from None
    except BaseException:
        _discard(ts_merge, out)
        raise
    rec = None if ts_merge is None else ts_merge.stream.record  # the time series, hashed as it was written
    manifest["published"] = publish.publish(stage, out, None if rec is None else {ts_merge.stream.path.name: rec})
    manifest["end"] = store.now_iso()
    manifest["wall_s_last_session"] = round(time.perf_counter() - t_start, 3)
    store.write_json(out / "manifest.json", manifest)
    return RunResult(out, trials, pt, time.perf_counter() - t_start, len(chunks))


def _verified_and_finalized(chunk_dir: Path, spec: integrity.RunSpec, ts_merge: InOrderMerge | None,
                            merge: Callable[[], tuple[tables.Columns, tables.Columns]],
                            ) -> tuple[tables.Columns, tables.Columns]:  # fmt: skip
    """``merge()`` (:func:`finalize` into the staging directory) while another thread verifies the chunk files
    (``integrity.verify_chunks``: reading and hashing them, the GIL released), then the verification's verdict
    before the merge's own (:class:`integrity.IntegrityError` for a chunk that does not verify, even where the
    merge also failed on it); nothing is published before both are done."""
    from concurrent.futures import ThreadPoolExecutor

    failed: Exception | None = None
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="spmc-verify") as pool:
        verifying = pool.submit(integrity.verify_chunks, chunk_dir, spec)
        try:
            merged = merge()
        except Exception as exc:  # noqa: BLE001 - raised below, after the verification's verdict
            failed = exc
        v = verifying.result()
    integrity.check_complete(v, spec)
    if ts_merge is not None and ts_merge.keys != [c["first"] for c in v.chunks]:
        raise integrity.IntegrityError([f"{chunk_dir}: the verified chunks are not the ones this session merged"])
    if failed is not None:
        raise failed
    return merged


def _discard(ts_merge: InOrderMerge | None, out: Path) -> None:
    """Drop a session's unpublished merge: the partial time series and the staging directory."""
    if ts_merge is not None:
        ts_merge.abort()
    publish.remove_stages(out)


def compile_note() -> list[str]:
    """``["compiling kernels, first run only ..."]`` when Numba's cache lacks the kernels, else ``[]``."""
    from . import warm

    return [] if warm.kernels_cached() else [warm.COMPILING]


def _read_manifest(out: Path) -> dict:
    """A run directory's manifest; :class:`RunError` in one line naming the file for anything unreadable."""
    p = out / "manifest.json"
    if not p.is_file():
        raise RunError(f"{out}: not a run directory (no manifest.json); nothing to resume")
    try:
        m = json.loads(p.read_bytes())
    except (OSError, ValueError) as exc:  # ValueError: not JSON, not UTF-8
        raise RunError(f"{p}: unreadable manifest ({exc})") from None
    if not isinstance(m, dict):
        raise RunError(f"{p}: not a run's manifest (not a JSON object)")
    if m.get("kind") != "run":
        raise RunError(f"{out}: not a run directory made by 'spmc run'")
    checks = {"trials": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 1,
              "seed": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
              "timeseries": lambda v: v in TIMESERIES_MODES, "scenario_hash": lambda v: isinstance(v, str),
              "backend": lambda v: v is None or isinstance(v, dict), "chunks": lambda v: isinstance(v, list)}  # fmt: skip
    for key, ok in checks.items():
        if key in m and not ok(m[key]):
            raise RunError(f"{p}: {key}: {json.dumps(m[key])[:60]} is not valid (a damaged manifest)")
    if not isinstance(m.get("trials"), int):
        raise RunError(f"{p}: trials: missing (a damaged manifest)")
    return m


def recorded_timeseries(out: Path) -> str:
    """The ``--timeseries`` mode a run was started with."""
    return str(_read_manifest(out).get("timeseries", "full"))


def recorded_kernels(out: Path) -> str:
    """The kernels a run was started with (runs that predate the record: numpy)."""
    return _recorded_kernels(_read_manifest(out))


def _recorded_kernels(manifest: dict) -> str:
    return str((manifest.get("backend") or {}).get("kernels") or "numpy")


def load_run_scenario(out: Path) -> Scenario:
    """The resolved scenario stored in a run directory (:class:`RunError` in one line naming the file)."""
    from ..config.loader import ScenarioError, load_scenario

    p = out / "config.yaml"
    if not p.is_file():
        raise RunError(f"{out}: no config.yaml")
    try:
        return load_scenario(p)
    except ScenarioError as exc:
        more = f" (and {len(exc.problems) - 1} more)" if len(exc.problems) > 1 else ""
        raise RunError(f"{exc.problems[0]}{more}") from None
