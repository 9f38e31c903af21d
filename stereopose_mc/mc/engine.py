"""The Monte Carlo engine: chunks of trials -> joblib (loky/threading) or Dask -> files.

A run directory holds (see docs/outputs.md):

- ``config.yaml`` (the resolved scenario) and ``manifest.json`` (version, git revision,
  root seed, trial count, filters, host, start/end, scenario hash, per-chunk timings);
- ``chunks/``: one ``trials-<first>-<last>.parquet`` (+ ``timeseries-...``, ``timing-...``)
  per finished chunk, each written atomically (temporary name, then rename) by the
  driver as soon as the chunk finishes, so a run killed at any moment loses at most
  the chunks in flight;
- after all chunks: ``trials.parquet``, ``timeseries.parquet``, ``timing.parquet`` and
  the percentile tables, merged from the chunk files in trial order.

Determinism: trial ``j`` draws only from the ``j``-th ``SeedSequence`` child of the root
seed, and every kernel treats the trials of a chunk independently, so the merged
tables are the same bytes for any ``--jobs``, ``--chunk-size``, backend or resume.
Wall-clock timings are kept out of ``trials.parquet`` (they are in ``timing.parquet``
and the manifest) for that reason.
"""

from __future__ import annotations

import functools
import hashlib
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import pandas as pd
import yaml
from threadpoolctl import threadpool_limits

from typing import NamedTuple

from ..config.resolve import FilterSetup, Setup, filter_setup_of, setup_of
from ..config.schema import SCHEMA_VERSION, Scenario
from ..outputs import rundir, tables
from ..sim import measurements as meas
from ..sim.truth import Truth, simulate_truth
from .trial import Bounds, run_chunk

TIMESERIES_MODES = ("none", "summary", "full")
SUMMARY_TRIALS = 100  # trials kept in timeseries.parquet with --timeseries summary


class RunError(Exception):
    """A run that cannot start or resume as asked (bad directory, changed scenario...)."""


def scenario_hash(scn: Scenario) -> str:
    """SHA-256 of the scenario's canonical JSON, without the trial count."""
    d = scn.model_dump(mode="json")
    d.pop("trials", None)
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
    """Resolve a scenario and compute its (trial-independent) truth and exact measurements."""
    setup = setup_of(scn)
    truth = simulate_truth(setup)
    exact = meas.noise_free(setup, truth)
    filters = [filter_setup_of(f, setup) for f in scn.filters]
    d = scn.divergence
    bounds = Bounds(d.rho_m, d.rho_dot_mps, d.omega_degps, d.k, d.nis_ratio, d.nis_window_steps, d.nis_start_s,
                    d.sigma_ratio, d.nees_factor)  # fmt: skip
    return Prepared(scn, setup, truth, exact, filters, bounds)


@functools.lru_cache(maxsize=4)
def _prepared(scenario_json: str) -> Prepared:
    """``prepare`` computed once per process and scenario (chunks of a run share it)."""
    return prepare(Scenario.model_validate_json(scenario_json))


@dataclass
class ChunkOutput:
    trials: np.ndarray
    trials_df: pd.DataFrame
    timeseries_df: pd.DataFrame | None
    timing_df: pd.DataFrame
    wall_s: float
    diverged: int


def compute_chunk(scenario_json: str, trials: np.ndarray, timeseries: str) -> ChunkOutput:
    """Run one chunk of trials (any process): pure function of its arguments.

    BLAS runs single-threaded here: a multithreaded BLAS splits a product or a solve
    differently with the thread count, which changes the last bits of the results.
    Parallelism comes from the chunks instead.
    """
    with threadpool_limits(limits=1):
        scn, setup, truth, exact, filters, bounds = _prepared(scenario_json)
        res = run_chunk(scn.seed, np.asarray(trials), setup, truth, exact, filters, bounds)
    tdf = tables.trials_frame(res, truth.t, setup.window_start, scn.seed)
    ts = None
    if timeseries != "none":
        keep = None if timeseries == "full" else (np.asarray(trials) < SUMMARY_TRIALS)
        ts = tables.timeseries_frame(res, truth.t, keep)
        # filter-major blocks -> (trial, filter in scenario order, step), as in the merged file
        ts = ts.sort_values("trial", kind="stable").reset_index(drop=True) if len(ts) else None
    first = int(np.min(trials))
    timing = tables.timing_frame(res, first)
    return ChunkOutput(np.asarray(trials), tdf, ts, timing, res.runtime_s, int(tdf["diverged"].sum()))


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


def done_trials(chunk_dir: Path) -> np.ndarray:
    """Trials already present in finished chunk files."""
    out = []
    for p in sorted(chunk_dir.glob("trials-*.parquet")):
        a, b = p.stem.split("-")[1:3]
        out.append(np.arange(int(a), int(b) + 1))
    return np.concatenate(out) if out else np.zeros(0, np.int64)


@dataclass
class RunOptions:
    trials: int | None = None
    seed: int | None = None
    jobs: int = 1
    chunk_size: int = 50
    backend: str = "loky"
    scheduler: str | None = None
    timeseries: str = "full"
    overwrite: bool = False
    resume: bool = False
    command: list[str] = field(default_factory=lambda: list(sys.argv))


@dataclass
class RunResult:
    out: Path
    trials: pd.DataFrame
    percentiles: pd.DataFrame
    wall_s: float
    chunks_run: int


Progress = Callable[[int, int, int], None]  # (trials done, total, diverged so far)


def _parquet_meta(scn: Scenario, shash: str, kind: str) -> dict[str, str]:
    return {"stereopose_mc.schema_version": str(SCHEMA_VERSION), "stereopose_mc.table": kind,
            "stereopose_mc.scenario": scn.name, "stereopose_mc.scenario_hash": shash}  # fmt: skip


def _write_chunk(chunk_dir: Path, out: ChunkOutput, meta: dict[str, str]) -> None:
    # the trials file is the chunk's commit marker: written last
    if out.timeseries_df is not None and len(out.timeseries_df):
        rundir.write_parquet(chunk_dir / _chunk_name("timeseries", out.trials), out.timeseries_df, meta)
    rundir.write_parquet(chunk_dir / _chunk_name("timing", out.trials), out.timing_df, meta)
    rundir.write_parquet(chunk_dir / _chunk_name("trials", out.trials), out.trials_df, meta)


def _iterate(scenario_json: str, chunks: list[np.ndarray], opts: RunOptions) -> Iterable[ChunkOutput]:
    """Chunk outputs as they finish, in any order."""
    if opts.jobs == 1 and opts.backend != "dask":
        for c in chunks:
            yield compute_chunk(scenario_json, c, opts.timeseries)
        return
    from joblib import Parallel, delayed, parallel_config

    calls = (delayed(compute_chunk)(scenario_json, c, opts.timeseries) for c in chunks)
    if opts.backend == "dask":
        try:
            from dask.distributed import Client, LocalCluster
        except ImportError:  # pragma: no cover - depends on the optional extra
            raise RunError("--backend dask needs the optional extra: pip install 'stereopose_mc[dask]'") from None
        cluster = None
        if opts.scheduler:
            client = Client(opts.scheduler)
        else:
            cluster = LocalCluster(n_workers=max(1, opts.jobs), threads_per_worker=1, processes=True,
                                   dashboard_address=None)  # fmt: skip
            client = Client(cluster)
        try:
            with parallel_config(backend="dask"):
                yield from Parallel(return_as="generator_unordered")(calls)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
        return
    with parallel_config(backend=opts.backend, n_jobs=opts.jobs):
        yield from Parallel(return_as="generator_unordered")(calls)


def finalize(out: Path, scn: Scenario, shash: str, filter_order: list[str]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Merge chunk files into the run's tables and write the percentile tables."""
    order = {name: i for i, name in enumerate(filter_order)}

    def fsort(df):
        df["_f"] = df["filter"].map(order)
        return df

    files = sorted((out / "chunks").glob("trials-*.parquet"))
    trials = pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)
    trials = fsort(trials).sort_values(["trial", "_f"], kind="stable").drop(columns="_f").reset_index(drop=True)
    rundir.write_parquet(out / "trials.parquet", trials, _parquet_meta(scn, shash, "trials"))
    files = sorted((out / "chunks").glob("timing-*.parquet"))
    if files:
        df = fsort(pd.concat([pd.read_parquet(f) for f in files], ignore_index=True))
        df = df.sort_values(["trial", "_f"], kind="stable").drop(columns="_f").reset_index(drop=True)
        rundir.write_parquet(out / "timing.parquet", df, _parquet_meta(scn, shash, "timing"))
    # the time series can be large: streamed chunk by chunk (each chunk file is already
    # sorted by trial, filter, step, and the chunks are disjoint trial ranges, so file
    # order by first trial is trial order)
    files = sorted((out / "chunks").glob("timeseries-*.parquet"))
    if files:
        rundir.write_parquet_stream(out / "timeseries.parquet", files, _parquet_meta(scn, shash, "timeseries"))
    pt = tables.percentile_table(trials, list(scn.percentiles))
    rundir.atomic_write_text(out / "percentiles.csv", pt.to_csv(index=False, float_format="%.10g"))
    rundir.write_parquet(out / "percentiles.parquet", pt, _parquet_meta(scn, shash, "percentiles"))
    rundir.atomic_write_text(out / "percentiles.md", f"# {scn.name}: percentiles of per-trial mean errors\n\n"
                             + tables.percentiles_markdown(pt, trials))  # fmt: skip
    return trials, pt


def run(scn: Scenario, out: Path, opts: RunOptions, progress: Progress | None = None) -> RunResult:
    """Run (or resume) a Monte Carlo campaign into ``out``."""
    t_start = time.perf_counter()
    if opts.trials is not None or opts.seed is not None:
        scn = scn.model_copy(update={k: v for k, v in (("trials", opts.trials), ("seed", opts.seed)) if v is not None})
    if opts.timeseries not in TIMESERIES_MODES:
        raise RunError(f"--timeseries must be one of {', '.join(TIMESERIES_MODES)}")
    if opts.chunk_size < 1 or opts.jobs < 1:
        raise RunError("--jobs and --chunk-size must be at least 1")
    shash = scenario_hash(scn)
    chunk_dir = out / "chunks"
    if opts.resume:
        manifest = _read_manifest(out)
        if manifest.get("scenario_hash") != shash:
            raise RunError(
                f"{out}: the scenario differs from the one this run was started with "
                f"(hash {manifest.get('scenario_hash', '?')[:12]} vs {shash[:12]}); start a new run instead"
            )
        if manifest.get("timeseries") != opts.timeseries:
            raise RunError(f"{out}: this run was started with --timeseries {manifest.get('timeseries')}")
        scn = scn.model_copy(update={"trials": int(manifest["trials"])})
    else:
        rundir.prepare_dir(out, opts.overwrite)
        chunk_dir.mkdir()
        rundir.atomic_write_text(out / "config.yaml", yaml.safe_dump(scn.model_dump(mode="json"), sort_keys=False))
        manifest = rundir.base_manifest(opts.command)
        manifest.update(
            kind="run", scenario=scn.name, scenario_hash=shash, seed=scn.seed, trials=scn.trials,
            filters=[f.label for f in scn.filters], state_dim=13 + 3 * len(scn.target.feature_points_m) + 2,
            timeseries=opts.timeseries, start=rundir.now_iso(),
            end=None, chunks=[],
        )  # fmt: skip
        rundir.write_json(out / "manifest.json", manifest)
    done = done_trials(chunk_dir)
    todo = np.setdiff1d(np.arange(scn.trials), done)
    chunks = plan_chunks(todo, opts.chunk_size)
    scenario_json = scn.model_dump_json()
    meta = _parquet_meta(scn, shash, "chunk")
    n_done, n_div = int(done.size), 0
    if progress:
        progress(n_done, scn.trials, n_div)
    for co in _iterate(scenario_json, chunks, opts):
        _write_chunk(chunk_dir, co, meta)
        n_done += co.trials.size
        n_div += co.diverged
        manifest.setdefault("chunks", []).append(
            {"first": int(co.trials[0]), "last": int(co.trials[-1]), "wall_s": round(co.wall_s, 4),
             "jobs": opts.jobs, "backend": opts.backend}  # fmt: skip
        )
        rundir.write_json(out / "manifest.json", manifest)
        if progress:
            progress(n_done, scn.trials, n_div)
    trials, pt = finalize(out, scn, shash, [f.label for f in scn.filters])
    manifest["end"] = rundir.now_iso()
    manifest["wall_s_last_session"] = round(time.perf_counter() - t_start, 3)
    rundir.write_json(out / "manifest.json", manifest)
    return RunResult(out, trials, pt, time.perf_counter() - t_start, len(chunks))


def _read_manifest(out: Path) -> dict:
    p = out / "manifest.json"
    if not p.is_file():
        raise RunError(f"{out}: not a run directory (no manifest.json); nothing to resume")
    try:
        m = json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise RunError(f"{p}: unreadable manifest ({exc})") from None
    if m.get("kind") != "run":
        raise RunError(f"{out}: not a run directory made by 'spmc run'")
    return m


def load_run_scenario(out: Path) -> Scenario:
    """The resolved scenario stored in a run directory."""
    p = out / "config.yaml"
    if not p.is_file():
        raise RunError(f"{out}: no config.yaml")
    return Scenario.model_validate(yaml.safe_load(p.read_text()))

