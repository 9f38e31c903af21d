"""``spmc sweep``: whole campaigns over a grid (or zipped list) of scenario values."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from .app import CHUNK_HELP, JOBS_HELP, KERNELS_HELP, app, fail


@app.command()
def sweep(
    scenario: Path = typer.Argument(..., help="scenario YAML file, or a sweep file (configs/sweeps/*.yaml)"),
    sets: Optional[list[str]] = typer.Option(None, "--set", help="PATH=V1,V2,... (repeat for a grid); PATH like a.b or a.b[1]"),
    out: Path = typer.Option(..., "--out", help="sweep directory (one run directory per point below it)"),
    zipped: bool = typer.Option(False, "--zip", help="pair the --set lists (same length) instead of a grid"),
    trials: Optional[int] = typer.Option(None, "--trials", min=1, help="trials per point (default: the scenario's)"),
    jobs: Optional[int] = typer.Option(None, "--jobs", "-j", min=1, help=JOBS_HELP),
    chunk_size: Optional[int] = typer.Option(None, "--chunk-size", min=1, help=CHUNK_HELP),
    kernels: Optional[str] = typer.Option(None, "--kernels", help=KERNELS_HELP + "; a resumed point keeps its own"),
    timeseries: str = typer.Option("summary", "--timeseries", help="none | summary | full (per point)"),
    report: bool = typer.Option(True, "--report/--no-report", help="write the sweep report at the end"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress output"),
) -> None:
    """Run a campaign per point of a grid of scenario values into DIR; rerun the command to resume.

    Writes DIR/sweep.json, one run directory per point, DIR/percentiles.csv (all points;
    `spmc compare` takes two sweeps) and the sweep report (DIR/report.html, sweep.csv).
    """
    import time

    from .. import api
    from .progress import eta_text, progress_reporter

    ran = {"points": 0, "t0": 0.0}  # the points that ran (or resumed) so far, and when the first started

    def on_point(i, n, p, what):
        if not quiet:
            vals = ", ".join(f"{k}={v}" for k, v in p.values.items())
            line = f"[{i + 1}/{n}] {p.name} ({vals}): " + {"done": "finished, skipped", "run": "running",
                                                           "resume": "resuming"}[what]  # fmt: skip
            if what != "done":  # the sweep's time so far and, from the second point run, the rest at the same pace
                now = time.perf_counter()
                if not ran["points"]:
                    ran["t0"] = now
                eta = eta_text(now - ran["t0"], ran["points"], ran["points"] + n - i)
                ran["points"] += 1
                line += f"; sweep: {eta}" if eta else ""
            typer.echo(line)

    try:
        res = api.sweep(scenario, sets, out=out, zip=zipped, trials=trials, jobs=jobs, chunk_size=chunk_size,
                        kernels=kernels, timeseries=timeseries, on_point=on_point, progress_of=lambda p: progress_reporter(p.name, quiet),
                        command=list(sys.argv))  # fmt: skip
        if report:
            typer.echo(str(res.report()))
    except api.SpmcError as exc:
        fail(exc.lines)
    except KeyboardInterrupt:
        typer.echo("\ninterrupted: finished points and chunks are kept; rerun the same command to resume", err=True)
        raise typer.Exit(130) from None
    if not quiet:
        typer.echo(f"{len(res.ran) + len(res.skipped)} points ({len(res.ran)} run, {len(res.skipped)} already done) -> {out}")
