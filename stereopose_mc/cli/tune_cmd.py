"""``spmc tune``: calibrate a filter's process noise from Monte Carlo NEES/NIS."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import KERNELS_HELP, app, fail


@app.command()
def tune(
    scenario: Path = typer.Argument(..., help="scenario YAML file"),
    filter_label: str = typer.Option(..., "--filter", help="label of the filter entry to tune (its name or type)"),
    trials: int = typer.Option(30, "--trials", help="trials per evaluation (the same ones every time)"),
    out: Optional[Path] = typer.Option(None, "--out", help="write the tuned filter entry (YAML) here"),
    max_evaluations: int = typer.Option(40, "--max-evaluations", help="budget of Monte Carlo evaluations"),
    kernels: Optional[str] = typer.Option(None, "--kernels", help=KERNELS_HELP),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress output"),
) -> None:
    """Tune the Q block scales of one filter so its NEES and NIS are consistent (docs/filters.md, Tuning)."""
    from .. import api

    def progress(i: int, ev, what: str) -> None:
        if not quiet:
            typer.echo(f"[{i}/{max_evaluations}] {what}: cost {ev.cost:.3g}, NEES/dof gauge "
                       f"{ev.nees.get('nees_gauge', float('nan')):.3g}, NIS/dof {ev.nis:.3g}, lost {ev.lost}", err=True)  # fmt: skip

    try:
        res = api.tune(scenario, filter_label, trials=trials, max_evaluations=max_evaluations, out=out,
                       kernels=kernels, progress=progress)  # fmt: skip
    except api.SpmcError as exc:
        fail(exc.lines)
    typer.echo(res.table.to_string(float_format=lambda v: f"{v:.3g}"))
    typer.echo("\n# tuned filter entry (paste into the scenario's filters):\n" + res.yaml)
    if out is not None:
        typer.echo(f"wrote {out}")
