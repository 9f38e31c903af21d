"""``spmc export``: a run's tables as CSV (with units sidecars), MATLAB .mat or Parquet."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import app, fail


@app.command()
def export(
    run_dir: Path = typer.Argument(..., help="a run directory"),
    fmt: str = typer.Option(..., "--format", help="csv (+ <table>.units.csv) | mat (one struct per table) | parquet"),
    tables: Optional[str] = typer.Option(None, "--tables", help="comma-separated: trials,timeseries,percentiles,timing "
                                         "(default: every table the run has)"),
    out: Optional[Path] = typer.Option(None, "--out", help="output directory (default RUN/export)"),
    overwrite: bool = typer.Option(False, "--overwrite", help="replace files that exist"),
) -> None:
    """Export a run's tables for other tools; every file is written atomically (docs/api.md, Exports)."""
    from .. import api

    names = [t.strip() for t in tables.split(",") if t.strip()] if tables is not None else None
    if names is not None and not names:
        fail("--tables: give at least one table name")
    try:
        written = api.export(run_dir, fmt, names, out, overwrite)
    except api.SpmcError as exc:
        fail(exc.lines)
    for p in written:
        typer.echo(str(p))
