"""``spmc run``, ``spmc rerun`` (Monte Carlo engine)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from .app import CHUNK_HELP, JOBS_HELP, KERNELS_HELP, app, fail, load_or_exit


@app.command()
def run(
    scenario: Optional[Path] = typer.Argument(None, help="scenario YAML file (omit with --resume)"),
    trials: Optional[int] = typer.Option(None, "--trials", min=1, help="number of trials (default: the scenario's)"),
    seed: Optional[int] = typer.Option(None, "--seed", min=0, max=2**63 - 1, help="root seed (default: the scenario's)"),
    out: Optional[Path] = typer.Option(None, "--out", help="run directory (default runs/<scenario name>)"),
    jobs: Optional[int] = typer.Option(None, "--jobs", "-j", min=1, help=JOBS_HELP),
    chunk_size: Optional[int] = typer.Option(None, "--chunk-size", min=1, help=CHUNK_HELP),
    backend: Optional[str] = typer.Option(None, "--backend", help="auto (default: with the compiled kernels, worker "
                                          "processes forked from this one on Linux, else threads; loky processes with "
                                          "numpy) | fork | threading | loky | dask"),
    kernels: Optional[str] = typer.Option(None, "--kernels", help=KERNELS_HELP + "; on --resume, the run's"),
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
    from .. import api
    from .progress import figure_progress, progress_reporter

    if resume is not None:
        if scenario is not None:
            fail("give either a SCENARIO or --resume DIR, not both")
        if out is not None and out.resolve() != resume.resolve():
            fail("--out and --resume conflict: a resumed run stays in its directory")
        if overwrite:
            fail("--resume and --overwrite conflict: resume keeps the finished chunks")
        out = resume
    elif scenario is None:
        fail("missing SCENARIO (or --resume DIR)")
    try:
        scn = api.Run(resume).scenario if resume is not None else load_or_exit(scenario)
    except api.SpmcError as exc:
        fail(exc.lines)
    label = scn.name
    out = out or Path("runs") / label
    opts = dict(trials=trials, seed=seed, jobs=jobs, chunk_size=chunk_size, backend=backend or "auto", kernels=kernels,
                scheduler=scheduler, command=list(sys.argv), say=lambda line: typer.echo(f"note: {line}", err=True))
    if resume is None:
        from ..config.warnings import process_noise_notes

        for loc, line in process_noise_notes(scn):  # what `process_noise: auto` chose
            opts["say"](f"{scn.filters[loc[1]].label}: {line}")
    try:
        with progress_reporter(label, quiet) as prog:
            if resume is not None:
                r = api.resume(resume, timeseries=timeseries, progress=prog, **opts)
            else:
                r = api.run(scn, out=out, timeseries=timeseries or "full", overwrite=overwrite,
                            progress=prog, **opts)  # fmt: skip
        if report:
            with figure_progress(label, quiet) as fprog:
                r.report(fprog, jobs)  # (--jobs: the figures' processes too; default the cores available)
    except api.SpmcError as exc:
        fail(exc.lines)
    except KeyboardInterrupt:
        typer.echo(f"\ninterrupted: finished chunks are kept in {out}/chunks; continue with: spmc run --resume {out}",
                   err=True)  # fmt: skip
        raise typer.Exit(130) from None
    if not quiet:
        typer.echo(r.summary())
        typer.echo(f"\n{r.n_trials} trials in {r.wall_s:.1f} s -> {out}")


@app.command()
def rerun(
    run_dir: Path = typer.Argument(..., help="a run directory"),
    trial: int = typer.Option(..., "--trial", min=0, help="the trial to reproduce"),
    out: Optional[Path] = typer.Option(None, "--out", help="write the trial's full time series here (Parquet)"),
) -> None:
    """Reproduce one trial of a run exactly, from its seed; check it against trials.parquet."""
    from .. import api

    try:
        res = api.Run(run_dir).rerun(trial, out)
    except api.SpmcError as exc:
        fail(exc.lines)
    for line in res.lines:
        typer.echo(line)
    if not res.identical:
        raise typer.Exit(1)
