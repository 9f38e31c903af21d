"""``spmc tune``: calibrate a filter's process noise from Monte Carlo NEES/NIS."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
import yaml

from .app import app, fail, load_or_exit


@app.command()
def tune(
    scenario: Path = typer.Argument(..., help="scenario YAML file"),
    filter_label: str = typer.Option(..., "--filter", help="label of the filter entry to tune (its name or type)"),
    trials: int = typer.Option(30, "--trials", help="trials per evaluation (the same ones every time)"),
    out: Optional[Path] = typer.Option(None, "--out", help="write the tuned filter entry (YAML) here"),
    max_evaluations: int = typer.Option(40, "--max-evaluations", help="budget of Monte Carlo evaluations"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress output"),
) -> None:
    """Tune the Q block scales of one filter so its NEES and NIS are consistent (docs/filters.md, Tuning)."""
    from ..studies import tuning

    scn = load_or_exit(scenario)
    if trials < 2:
        fail("--trials must be at least 2")
    if max_evaluations < 1:
        fail("--max-evaluations must be at least 1")
    if out is not None and (out.is_dir() or not out.parent.exists()):
        fail(f"{out}: --out must be a file in an existing directory")

    def progress(i: int, ev, what: str) -> None:
        if not quiet:
            typer.echo(f"[{i}/{max_evaluations}] {what}: cost {ev.cost:.3g}, NEES/dof gauge "
                       f"{ev.nees.get('nees_gauge', float('nan')):.3g}, NIS/dof {ev.nis:.3g}, lost {ev.lost}", err=True)  # fmt: skip

    try:
        res = tuning.tune(scn, filter_label, trials, max_evaluations, progress=progress)
    except tuning.TuneError as exc:
        fail(f"{scenario}: {exc}")
    typer.echo(tuning.comparison_table(res).to_string(float_format=lambda v: f"{v:.3g}"))
    text = yaml.safe_dump({"filters": [tuning.tuned_entry(scn, filter_label, res)]}, sort_keys=False)
    typer.echo("\n# tuned filter entry (paste into the scenario's filters):\n" + text)
    if out is not None:
        out.write_text(text)
        typer.echo(f"wrote {out}")
