"""``spmc run``, ``spmc rerun`` (Monte Carlo engine)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from .app import app, fail, load_or_exit


@app.command()
def run(
    scenario: Optional[Path] = typer.Argument(None, help="scenario YAML file (omit with --resume)"),
    trials: Optional[int] = typer.Option(None, "--trials", min=1, help="number of trials (default: the scenario's)"),
    seed: Optional[int] = typer.Option(None, "--seed", min=0, help="root seed (default: the scenario's)"),
    out: Optional[Path] = typer.Option(None, "--out", help="run directory (default runs/<scenario name>)"),
    jobs: int = typer.Option(1, "--jobs", "-j", min=1, help="parallel workers"),
    chunk_size: Optional[int] = typer.Option(None, "--chunk-size", min=1, help="trials stepped together per chunk "
                                             "(default 50; with --kernels compiled: trials / jobs, at most 250)"),
    backend: Optional[str] = typer.Option(None, "--backend", help="auto (default: threads with --kernels compiled, "
                                          "else loky processes) | loky | threading | dask"),
    kernels: Optional[str] = typer.Option(None, "--kernels", help="numpy (default; the reference) | compiled (Numba, "
                                          "threads; same results to round-off: docs/performance.md); on --resume, the run's"),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Dask scheduler address, implies --backend dask "
                                            "(default with dask: a LocalCluster); see docs/distributed.md"),
    timeseries: Optional[str] = typer.Option(None, "--timeseries", help="none | summary (first 100 trials) | full "
                                             "(default full; on --resume, the run's)"),
    resume: Optional[Path] = typer.Option(None, "--resume", help="resume this run directory (runs missing trials)"),
    overwrite: bool = typer.Option(False, "--overwrite", help="replace an existing run directory"),
    report: bool = typer.Option(True, "--report/--no-report", help="write figures and report.html at the end"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress output"),
) -> None:
    """Run a Monte Carlo campaign: every filter of the scenario on every trial."""
    from ..mc import engine
    from ..outputs import tables
    from ..outputs.rundir import RunDirError
    from .progress import figure_progress, progress_reporter

    if scheduler is not None and backend not in (None, "dask"):
        fail(f"--scheduler is a Dask scheduler's address: it needs --backend dask, not --backend {backend}")
    backend = backend or ("dask" if scheduler is not None else "auto")
    if backend not in ("auto", "loky", "threading", "dask"):
        fail(f"--backend must be auto, loky, threading or dask (got {backend!r})")
    if kernels not in (None, "numpy", "compiled"):
        fail(f"--kernels must be numpy or compiled (got {kernels!r})")
    if resume is not None:
        if scenario is not None:
            fail("give either a SCENARIO or --resume DIR, not both")
        if out is not None and out.resolve() != resume.resolve():
            fail("--out and --resume conflict: a resumed run stays in its directory")
        try:
            scn = engine.load_run_scenario(resume)
            timeseries = timeseries or engine.recorded_timeseries(resume)
        except (engine.RunError, ValueError) as exc:
            fail(str(exc))
        out = resume
    else:
        if scenario is None:
            fail("missing SCENARIO (or --resume DIR)")
        scn = load_or_exit(scenario)
        out = out or Path("runs") / scn.name
    opts = engine.RunOptions(trials=trials, seed=seed, jobs=jobs, chunk_size=chunk_size, backend=backend, kernels=kernels,
                             scheduler=scheduler, timeseries=timeseries or "full", overwrite=overwrite,
                             resume=resume is not None, command=list(sys.argv),
                             say=lambda line: typer.echo(f"note: {line}", err=True))  # fmt: skip
    try:
        with progress_reporter(scn.name, quiet) as prog:
            res = engine.run(scn, out, opts, prog)
    except (engine.RunError, RunDirError) as exc:
        fail(str(exc))
    except KeyboardInterrupt:
        typer.echo(f"\ninterrupted: finished chunks are kept in {out}/chunks; continue with: spmc run --resume {out}",
                   err=True)  # fmt: skip
        raise typer.Exit(130) from None
    if report:
        from ..outputs import report as rep
        from ..outputs.runlock import locked

        try:
            with locked(out, "spmc report"), figure_progress(scn.name, quiet) as fprog:
                rep.build_run_report(out, fprog)
        except (rep.ReportError, RunDirError) as exc:
            fail(str(exc))
    if not quiet:
        pt, tr = res.percentile_columns, res.trials_columns
        for label in dict.fromkeys(pt["filter"].tolist()):
            first = list(pt["filter"]).index(label)
            n, nd = int(pt["trials"][first]), int(pt["diverged"][first])
            typer.echo(f"\n{label}: per-trial mean errors over t >= {scn.time.error_window_start_s:g} s, "
                       f"{n - nd}/{n} trials converged ({nd} diverged)")  # fmt: skip
            typer.echo(tables.format_table(pt, label, "converged"))
            if nd:
                typer.echo("all trials (diverged = inf):")
                typer.echo(tables.format_table(pt, label, "all"))
        if "invalid" in tr and tr["invalid"].any():
            bad = len(set(tr["trial"][tr["invalid"].astype(bool)].tolist()))
            typer.echo(f"\n{bad} trial(s) drew an invalid scenario (counted as diverged at step 0; "
                       "column 'invalid', reason 'invalid draw: ...' in trials.parquet)")  # fmt: skip
        typer.echo(f"\n{len(set(tr['trial'].tolist()))} trials in {res.wall_s:.1f} s -> {out}")


@app.command()
def rerun(
    run_dir: Path = typer.Argument(..., help="a run directory"),
    trial: int = typer.Option(..., "--trial", min=0, help="the trial to reproduce"),
    out: Optional[Path] = typer.Option(None, "--out", help="write the trial's full time series here (Parquet)"),
) -> None:
    """Reproduce one trial of a run exactly, from its seed; check it against trials.parquet."""
    from ..mc import rerun as rr

    try:
        res = rr.rerun_trial(run_dir, trial, out)
    except rr.RerunError as exc:
        fail(str(exc))
    for line in res.lines:
        typer.echo(line)
    if not res.identical:
        raise typer.Exit(1)
