"""``spmc tune``: calibrate a filter's Q (and R, P0) from Monte Carlo NEES/NIS on the trials ``spmc run`` runs."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import JOBS_HELP, KERNELS_HELP, app, fail


@app.command()
def tune(
    scenario: Path = typer.Argument(..., help="scenario YAML file"),
    filter_label: str = typer.Option(..., "--filter", help="label of the filter entry to tune (its name or type)"),
    trials: int = typer.Option(30, "--trials", help="tuning trials per evaluation: 0..N-1 (the same every time)"),
    check_trials: Optional[int] = typer.Option(
        None, "--check-trials", help="held-back trials N..N+M-1 for the before/after check (default N; 0: none)"
    ),
    space: str = typer.Option(
        "q", "--tune", help="what to search, comma-separated: q (the six Q blocks), r (one factor on the filter's "
        "image and flow sigmas) or r_image / r_flow (each alone), p0 (a factor per initial_covariance block) or "
        "p0_all (one factor)",
    ),  # fmt: skip
    out: Optional[Path] = typer.Option(
        None, "--out", help="write the tuned filter entry (and initial_covariance, if tuned) as YAML here"
    ),
    max_evaluations: int = typer.Option(40, "--max-evaluations", help="budget of Monte Carlo evaluations"),
    kernels: Optional[str] = typer.Option(None, "--kernels", help=KERNELS_HELP),
    jobs: Optional[int] = typer.Option(None, "--jobs", "-j", min=1, help=JOBS_HELP),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress output"),
) -> None:
    """Tune one filter's Q (and R, P0) so its NEES and NIS are consistent, then check on held-back trials.

    Every evaluation runs the trials `spmc run --trials N+M` runs (dispersions, truth model, faults, gating, \
the measurement-based start); docs/filters.md, `spmc tune`.
    """
    import time

    from .. import api
    from .progress import eta_text

    t0 = time.perf_counter()

    def progress(i: int, ev, what: str) -> None:
        if not quiet:
            typer.echo(f"[{i}/{max_evaluations}] {what}: cost {ev.cost:.3g}, NEES/dof gauge "
                       f"{ev.nees.get('nees_gauge', float('nan')):.3g}, NIS/dof {ev.nis:.3g}, "
                       f"lost {ev.lost}/{ev.trials}; "
                       f"{eta_text(time.perf_counter() - t0, i, max_evaluations, at_most=True)}", err=True)  # fmt: skip

    try:
        res = api.tune(scenario, filter_label, trials=trials, max_evaluations=max_evaluations, out=out,
                       kernels=kernels, space=space, check_trials=check_trials, progress=progress,
                       jobs=jobs)  # fmt: skip
    except api.SpmcError as exc:
        fail(exc.lines)
    fmt = lambda v: f"{v:.0f}" if float(v).is_integer() and abs(v) < 1e6 else f"{v:.3g}"  # noqa: E731 (counts)
    r = res.result
    typer.echo(f"# tuning trials 0-{r.before.trials - 1} ({r.evaluations} evaluations)")
    typer.echo(res.table.to_string(float_format=fmt))
    if res.check is not None:
        typer.echo(f"\n# held-back trials {r.before.trials}-{r.before.trials + r.check_before.trials - 1} "
                   "(not used by the search)")  # fmt: skip
        typer.echo(res.check.to_string(float_format=fmt))
    typer.echo("\n# tuned filter entry (paste into the scenario):\n" + res.yaml)
    if out is not None:
        typer.echo(f"wrote {out}")
