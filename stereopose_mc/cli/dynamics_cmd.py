"""``spmc dynamics``: the dynamical-model studies of thesis chapter 2 (section 2.5)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from .app import app, fail, load_or_exit


def parse_points(text: str) -> tuple[int, ...]:
    """``"1,5,10"`` -> ``(1, 5, 10)``; every entry a positive integer."""
    try:
        pts = tuple(int(p) for p in text.split(",") if p.strip())
    except ValueError:
        pts = ()
    if not pts or any(p < 1 for p in pts):
        raise ValueError(f"--timing-points must be a comma-separated list of positive integers, got {text!r}")
    return pts


@app.command("dynamics")
def dynamics(
    scenario: Path = typer.Argument(..., help="scenario YAML file"),
    out: Optional[Path] = typer.Option(None, "--out", help="output directory (default runs/<name>-dynamics)"),
    overwrite: bool = typer.Option(False, "--overwrite", help="replace a non-empty output directory"),
    horizon: Optional[float] = typer.Option(
        None, "--horizon", help="seconds for the CW and coupled-model studies (default: one leader orbit)"
    ),
    timing_points: str = typer.Option("1,5,10,20,50,100", "--timing-points", help="feature-point counts to time"),
    repeats: int = typer.Option(5, "--repeats", help="timed runs per configuration (the shortest is reported)"),
    dock_time: float = typer.Option(80.0, "--dock-time", help="CW docking (intercept) time, s"),
) -> None:
    """Nonlinear vs CW, simplified vs coupled feature model, and cost vs N (thesis figs 2.3-2.10)."""
    from ..rundir.store import RunDirError
    from ..studies.dynamics_study import StudyOptions, run_dynamics, summary_lines

    problems = []
    try:
        pts = parse_points(timing_points)
    except ValueError as exc:
        problems.append(str(exc))
        pts = ()
    if horizon is not None and not horizon > 0:
        problems.append(f"--horizon must be positive, got {horizon}")
    if repeats < 1:
        problems.append(f"--repeats must be at least 1, got {repeats}")
    if not dock_time > 0:
        problems.append(f"--dock-time must be positive, got {dock_time}")
    if problems:
        fail(problems)
    scn = load_or_exit(scenario)
    out = out or Path("runs") / f"{scn.name}-dynamics"
    opts = StudyOptions(horizon_s=horizon, timing_points=pts, timing_repeats=repeats, dock_time_s=dock_time)
    try:
        r = run_dynamics(scn, out, opts, overwrite=overwrite, command=sys.argv)
    except RunDirError as exc:
        fail(str(exc))
    for line in summary_lines(r):
        typer.echo(line)
    if scn.truth_model is not None:  # perturbed truth: how far it is from the filters' model
        from ..config.resolve import setup_of
        from ..studies.truth_mismatch import summary_lines as mismatch_lines, write_mismatch

        df, _ = write_mismatch(setup_of(scn), out)
        for line in mismatch_lines(df):
            typer.echo(line)
    typer.echo(f"-> {out}")
