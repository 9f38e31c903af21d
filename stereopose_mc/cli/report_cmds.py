"""``spmc report`` (HTML reports of run directories) and ``spmc compare`` (percentile-table diff)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import app, fail


@app.command()
def report(
    paths: list[Path] = typer.Argument(..., help="run directories, or folders holding run directories"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress lines while figures are written"),
    jobs: Optional[int] = typer.Option(
        None, "--jobs", "-j", min=1, help="processes drawing the figures (default: the cores available to this process)"
    ),
) -> None:
    """Write figures/ and report.html for each run (from its tables; nothing is re-run).

    A folder of runs also gets an index.html comparing them side by side. Prints the
    paths written; a broken or partial run directory is an error (exit 2) listing what
    is missing.
    """
    from .. import api
    from .progress import figure_progress

    res = api.report(paths, lambda r: figure_progress(r.name, quiet), jobs)
    for w in res.written:
        typer.echo(str(w))
    if res.problems:
        fail(res.problems)


@app.command()
def compare(
    run: Path = typer.Argument(..., help="a run directory or a percentiles.csv"),
    baseline: Path = typer.Argument(..., help="the baseline: a run directory or a percentiles.csv"),
    rtol: float = typer.Option(1e-6, "--rtol", min=0.0, help="relative tolerance (of the baseline value)"),
    atol: float = typer.Option(0.0, "--atol", min=0.0, help="absolute tolerance"),
    population: str = typer.Option("both", "--population", help="converged | all | both"),
    show_all: bool = typer.Option(False, "--all", help="list every cell, not only those out of tolerance"),
) -> None:
    """Compare two percentile tables cell by cell; exit 1 if any cell is out of tolerance.

    A cell passes when |run - baseline| <= atol + rtol*|baseline| (inf equals inf, nan
    equals nan, nan against a number fails); rows or filters present in only one table
    fail. The diff is printed as a Markdown table.
    """
    from ..outputs import compare as cmp

    if population not in cmp.POPULATIONS:
        fail(f"--population must be converged, all or both (got {population!r})")
    try:
        res = cmp.compare_paths(run, baseline, rtol, atol, population)
    except cmp.CompareError as exc:
        fail(str(exc))
    typer.echo(cmp.format_comparison(res, show_all), nl=False)
    if not res.ok:
        raise typer.Exit(1)
