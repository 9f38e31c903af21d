"""``spmc observability``: the Hermann-Krener rank test (thesis ch. 4) or the filter-state Gramian.

Parses options and calls :mod:`stereopose_mc.studies.observability`, which returns the
``--json`` dict and its text form.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

from .app import app, echo_json, emit, fail, load_or_exit

DEFAULT_WEAK_COUNT = 5
"""How many of the weakest directions ``--filter-state`` describes by default."""

OBSERVABILITY_HELP = (
    "Hermann-Krener rank test of thesis ch. 4: state x = (w, I_x, I_y, I_z), output y = w, torque-free.\n\n"
    "Prints the rank of O = (grad L0h; grad L1h) (5 for generic w and I), its null space (the unobservable "
    "direction, proportional to (0, 0, 0, I_x, I_y, I_z): only inertia ratios are observable) and its "
    "singular values. Units: w in deg/s on input and rad/s in the output, I in kg m^2 (SI).\n\n"
    "With --filter-state SCENARIO: a numerical local observability analysis of the whole filter state "
    "along the scenario's true trajectory instead: the observability Gramian "
    "W = sum_k Phi(t_k,t_0)^T H_k^T R^-1 H_k Phi(t_k,t_0) of the filter's Jacobians (R: the truth's noise), "
    "scaled by sqrt(diag P0) and eigen-decomposed (quaternion-norm direction projected out, and the "
    "body-frame gauge unless --keep-gauge), its weakest directions by state element, and the CRLB "
    "sqrt(diag((W + P0^-1)^-1)) in SI units (rho m, rho_dot m/s, omega rad/s; summaries in deg/s and deg). "
    "See docs/observability.md."
)


@app.command(help=OBSERVABILITY_HELP)
def observability(
    omega_degps: tuple[float, float, float] = typer.Option(
        (-0.1, -0.1, 0.034),
        "--omega-degps",
        help="angular velocity w_x w_y w_z in principal axes, deg/s (default: case B)",
    ),
    inertia: tuple[float, float, float] = typer.Option(
        (0.83, 1.0, 1.083), "--inertia", help="principal moments I_x I_y I_z, kg m^2, > 0 (default: case B)"
    ),
    order: int = typer.Option(1, "--order", help="highest Lie derivative in O: 1 (thesis eq. 4.15) or 2"),
    rtol: float = typer.Option(1e-9, "--rtol", help="relative threshold on the scaled singular values for the rank"),
    as_json: bool = typer.Option(
        False, "--json", help="print one JSON object (rank, null_space, singular_values, ...)"
    ),
    filter_state: Optional[Path] = typer.Option(
        None,
        "--filter-state",
        help="scenario file: analyse the observability Gramian of the full filter state along its true "
        "trajectory (instead of the Hermann-Krener test)",
    ),
    duration_s: Optional[float] = typer.Option(
        None, "--duration-s", help="with --filter-state: horizon in s (default: the scenario's time.duration_s)"
    ),
    weak: int = typer.Option(
        DEFAULT_WEAK_COUNT, "--weak", help="with --filter-state: how many of the weakest directions to describe"
    ),
    keep_gauge: bool = typer.Option(
        False,
        "--keep-gauge",
        help="with --filter-state: do not project the body-frame gauge (rotating q and all P_i together) out "
        "of the eigen-analysis",
    ),
) -> None:
    """Hermann-Krener rank test of thesis ch. 4 (see OBSERVABILITY_HELP)."""
    if filter_state is not None:
        problems = []
        euler_defaults = ((-0.1, -0.1, 0.034), (0.83, 1.0, 1.083), 1, 1e-9)
        if (tuple(omega_degps), tuple(inertia), order, rtol) != euler_defaults:
            problems.append(
                "--omega-degps, --inertia, --order and --rtol belong to the Hermann-Krener test, not to --filter-state"
            )
        if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
            problems.append(f"--duration-s must be a positive number of seconds (got {duration_s})")
        if weak < 1:
            problems.append(f"--weak must be at least 1 (got {weak})")
        if problems:
            fail(problems)
        _filter_state_command(filter_state, duration_s, weak, keep_gauge, as_json)
        return
    problems = []
    if duration_s is not None or weak != DEFAULT_WEAK_COUNT or keep_gauge:
        problems.append("--duration-s, --weak and --keep-gauge need --filter-state SCENARIO")
    if order not in (1, 2):
        problems.append(f"--order must be 1 or 2 (got {order})")
    if not all(math.isfinite(w) for w in omega_degps):
        problems.append(f"--omega-degps must be finite (got {list(omega_degps)})")
    if not all(math.isfinite(i) and i > 0 for i in inertia):
        problems.append(f"--inertia must be three positive moments (got {list(inertia)})")
    elif 2 * max(inertia) > sum(inertia):
        problems.append(f"--inertia {' '.join(f'{i:g}' for i in inertia)}: the moments violate the triangle "
                        "inequality (no rigid body has them)")
    if not (math.isfinite(rtol) and 0 < rtol < 1):
        problems.append(f"--rtol must be in (0, 1) (got {rtol})")
    if problems:
        fail(problems)
    from ..studies.observability import euler_observability, rank_report_lines

    r = euler_observability(omega_degps, inertia, order, rtol)
    if as_json:
        echo_json(r)
        return
    from ..studies.jsonfmt import fmt_vec

    typer.echo("Hermann-Krener rank test (thesis ch. 4): x = [w_x, w_y, w_z, I_x, I_y, I_z], y = w, torque-free")
    typer.echo(
        f"w = {fmt_vec(omega_degps, '.6g')} deg/s, I = {fmt_vec(inertia, '.6g')} kg m^2, "
        f"Lie derivatives up to order {order}"
    )
    for line in rank_report_lines(r):
        typer.echo(line)
    if r["null_space_is_inertia_scale"]:
        typer.echo("the null space is [0, 0, 0, I_x, I_y, I_z]/|I|: only the inertia ratios are observable")


def _filter_state_command(path: Path, duration_s: float | None, weak: int, keep_gauge: bool, as_json: bool) -> None:
    """``--filter-state``: load the scenario (exit 2 if invalid), analyse, print."""
    from ..studies.observability import filter_state_lines, filter_state_observability

    s = load_or_exit(path)
    steps = None if duration_s is None else round(duration_s / s.time.dt_s)
    if steps is not None and steps < 1:
        fail([f"--duration-s {duration_s:g} is shorter than one step (time.dt_s = {s.time.dt_s:g} s)"])
    try:
        r = filter_state_observability(s, duration_s, weak=weak, fix_gauge=not keep_gauge)
    except ValueError as exc:
        fail([f"{path}: {exc}"])
    r["scenario_file"] = str(path)
    emit(r, filter_state_lines, as_json)

