"""``spmc validate`` and ``spmc simulate``."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from .app import app, fail, load_or_exit


@app.command()
def validate(files: list[Path] = typer.Argument(..., help="scenario YAML files")) -> None:
    """Check scenario files: ``ok: FILE`` per good file; one line per problem on stderr
    (``FILE:LINE: key.path: message``) and exit code 2 if any file has one. Warnings (``FILE:LINE: key.path:
    warning: ...``, config/warnings.py: a dispersion beyond P0 on the truth alone, features never in view) go
    to stderr too and leave the exit code 0, and so do notes (``... note: ...``: what ``process_noise: auto`` chose)."""
    from ..studies import sweep as sw
    from ..config import ScenarioError, load_scenario

    problems: list[str] = []
    for f in files:
        if sw.is_sweep_file(f):  # a sweep file: every point of its grid must be a valid scenario
            try:
                sw.build_points(*sw.load_sweep_file(f))
                typer.echo(f"ok: {f}")
            except sw.SweepError as exc:
                problems.append(str(exc))
            except ScenarioError as exc:
                problems.extend(str(p) for p in exc.problems)
            continue
        try:
            scn = load_scenario(f)
            typer.echo(f"ok: {f}")
        except ScenarioError as exc:
            problems.extend(str(p) for p in exc.problems)
            continue
        for w in _warnings(f, scn):
            typer.echo(str(w), err=True)
    if problems:
        fail(problems)


def _warnings(path: Path, scn) -> list:
    """``config.warnings`` of a valid scenario, and a warning when its cameras never see a feature point."""
    from ..config.warnings import scenario_warnings
    from ..mc import engine

    extra = []
    if not engine.prepare(scn).exact.visible.any():
        extra.append((("camera",), "no feature point is ever in view of the cameras (field of view, range, occlusion, "
                      "or points inside the body): the filters get no measurement and every trial will be lost"))  # fmt: skip
    return scenario_warnings(path, scn, extra)


@app.command()
def simulate(
    scenario: Path = typer.Argument(..., help="scenario YAML file"),
    out: Optional[Path] = typer.Option(None, "--out", help="output directory (default runs/<name>-sim)"),
    no_noise: bool = typer.Option(False, "--no-noise", help="write the exact measurements"),
    seed: Optional[int] = typer.Option(None, "--seed", min=0, max=2**63 - 1, help="root seed (default: the scenario's)"),
    overwrite: bool = typer.Option(False, "--overwrite", help="replace an existing output directory"),
    trial: Optional[int] = typer.Option(None, "--trial", min=0, help="trial j's truth (dispersed) and noise"),
) -> None:
    """Simulate the truth and one noisy measurement set of a scenario."""
    from ..rundir.store import RunDirError, check_replaceable
    from ..outputs.simulation import simulate as run_simulate

    scn = load_or_exit(scenario)
    out = out or Path("runs") / f"{scn.name}-sim"
    try:
        check_replaceable(out, overwrite)  # before any computation
        s = run_simulate(scn, out, noise=not no_noise, seed=seed, overwrite=overwrite, command=sys.argv, trial=trial)
    except (RunDirError, ValueError) as exc:
        fail(str(exc))
    typer.echo(
        f"{scn.name}: {s.steps} steps, {s.features} features, range {s.range_min:.2f}-{s.range_max:.2f} m, "
        f"visible {100 * s.visible_fraction:.1f}% -> {s.out}"
    )
