"""``spmc observability`` and ``spmc inertia`` (thesis chapters 4 and 7).

Each command parses its options, calls one typed function that does the work and
returns a plain ``dict`` (the ``--json`` object), and prints that dict as text or JSON.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Optional

import numpy as np
import typer

from .app import app, fail, load_or_exit  # noqa: F401

# --------------------------------------------------------------------------- helpers


def _num(x: float) -> float:
    """A float for JSON/printing, with negative zero made positive."""
    return float(x) + 0.0


def _vec(v) -> list[float]:
    return [_num(x) for x in np.asarray(v, dtype=float).reshape(-1)]


def _mat(m) -> list[list[float]]:
    return [_vec(row) for row in np.asarray(m, dtype=float)]


def _fmt(x: float, spec: str) -> str:
    """``x`` formatted, without the sign of a value that prints as zero (``-0.000000``)."""
    s = f"{x:{spec}}"
    return f"{0.0:{spec}}" if s.strip().startswith("-") and float(s) == 0.0 else s


def _fmt_vec(v, spec: str = "10.6g") -> str:
    return "[" + ", ".join(_fmt(x, spec) for x in v) + "]"


def _echo_json(obj: dict[str, Any]) -> None:
    typer.echo(json.dumps(obj, allow_nan=False))


# --------------------------------------------------------------------------- observability


def euler_observability(omega_degps, inertia, order: int = 1, rtol: float | None = None) -> dict[str, Any]:
    """The thesis's ch. 4 Hermann-Krener test at ``[omega, inertia]`` as a JSON-ready dict.

    ``null_space`` is a list of unit vectors (one per unobservable direction) in the state
    ``[w_x, w_y, w_z, I_x, I_y, I_z]`` (rad/s, kg m^2); ``singular_values`` are those of ``O``
    in SI units; ``scaled_singular_values`` those that decide the rank (unit-free).
    """
    from ..core import observability as ob

    omega = np.deg2rad(np.asarray(omega_degps, dtype=float))
    inertia = np.asarray(inertia, dtype=float)
    res = ob.euler_rank_test(omega, inertia, order=order, rtol=ob.DEFAULT_RTOL if rtol is None else rtol)
    expected = inertia / np.linalg.norm(inertia)
    null = [res.null_space[:, i] for i in range(res.null_space.shape[1])]
    scale_only = len(null) == 1 and np.allclose(null[0], np.concatenate([np.zeros(3), expected]), atol=1e-8)
    return {
        "analysis": "euler",
        "state": list(ob.STATE_NAMES),
        "state_units": ["rad/s"] * 3 + ["kg m^2"] * 3,
        "omega_radps": _vec(omega),
        "inertia_kgm2": _vec(inertia),
        "order": order,
        "rows": int(3 * (order + 1)),
        "rank": res.rank,
        "null_space": [_vec(v) for v in null],
        "singular_values": _vec(res.singular_values),
        "scaled_singular_values": _vec(res.scaled_singular_values),
        "rtol": res.rtol,
        "null_space_is_inertia_scale": bool(scale_only),
    }


def _print_rank_report(r: dict[str, Any]) -> None:
    """Text form of a rank-test dict (shared by every observability analysis)."""
    n = len(r["state"])
    typer.echo(
        f"rank {r['rank']} of {n} (O is {r['rows']} x {n}; "
        f"relative threshold {r['rtol']:g} on the scaled singular values)"
    )
    typer.echo("singular values of O (SI entries): " + " ".join(f"{s:.4e}" for s in r["singular_values"]))
    typer.echo("scaled singular values (s/s_max): " + " ".join(f"{s:.4e}" for s in r["scaled_singular_values"]))
    if not r["null_space"]:
        typer.echo("null space: empty (locally weakly observable)")
        return
    names = ", ".join(r["state"])
    typer.echo(f"null space ({len(r['null_space'])} unobservable direction(s), unit vectors over {names}):")
    for v in r["null_space"]:
        typer.echo("  " + _fmt_vec(v, "9.6f"))


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
    if not (math.isfinite(rtol) and 0 < rtol < 1):
        problems.append(f"--rtol must be in (0, 1) (got {rtol})")
    if problems:
        fail(problems)
    r = euler_observability(omega_degps, inertia, order, rtol)
    if as_json:
        _echo_json(r)
        return
    typer.echo("Hermann-Krener rank test (thesis ch. 4): x = [w_x, w_y, w_z, I_x, I_y, I_z], y = w, torque-free")
    typer.echo(
        f"w = {_fmt_vec(omega_degps, '.6g')} deg/s, I = {_fmt_vec(inertia, '.6g')} kg m^2, "
        f"Lie derivatives up to order {order}"
    )
    _print_rank_report(r)
    if r["null_space_is_inertia_scale"]:
        typer.echo("the null space is [0, 0, 0, I_x, I_y, I_z]/|I|: only the inertia ratios are observable")


def _filter_state_command(path: Path, duration_s: float | None, weak: int, keep_gauge: bool, as_json: bool) -> None:
    """``--filter-state``: load the scenario (exit 2 if invalid), analyse, print."""
    from ..observability_study import filter_state_observability

    s = load_or_exit(path)
    steps = None if duration_s is None else round(duration_s / s.time.dt_s)
    if steps is not None and steps < 1:
        fail([f"--duration-s {duration_s:g} is shorter than one step (time.dt_s = {s.time.dt_s:g} s)"])
    try:
        r = filter_state_observability(s, duration_s, weak=weak, fix_gauge=not keep_gauge)
    except ValueError as exc:
        fail([f"{path}: {exc}"])
    r["scenario_file"] = str(path)
    if as_json:
        _echo_json(r)
    else:
        _print_filter_state(r)


def _e(x: float) -> str:
    return f"{x:.3e}"


def _print_filter_state(r: dict[str, Any]) -> None:
    """Text form of the ``--filter-state`` dict."""
    names = r["state_names"]
    typer.echo(
        f"Observability Gramian of the filter state along the true trajectory of {r['scenario']} "
        f"({r['scenario_file']}): {r['duration_s']:g} s, dt {r['dt_s']:g} s, {r['measurement_rows']} measurement rows, "
        f"pseudo-measurement {'on' if r['pseudo_measurement'] else 'off'}, "
        f"omega0 = {_fmt_vec(r['omega0_degps'], '.4g')} deg/s"
    )
    typer.echo("W = sum_k Phi(t_k,t_0)^T H_k^T R^-1 H_k Phi(t_k,t_0), R = the truth's noise; "
               "scaled W~ = S W S with S = sqrt(diag P0) (unit-free)")  # fmt: skip
    typer.echo(f"largest eigenvalue of W~: {_e(r['lambda_max'])}; values below are relative to it "
               f"(round-off floor n eps = {r['roundoff_floor'] / r['lambda_max']:.1e})")  # fmt: skip
    qn = r["q_norm"]
    typer.echo(
        f"quaternion norm direction: unobservable by construction (|H_k e_q| / |H_k| <= {qn['max_rel_H_eq']:.1e}); "
        f"Rayleigh quotient {qn['relative_rayleigh']:.1e} (discretization of Phi); projected out"
    )
    gauge = " ".join(f"{v:.1e}" for v in r["gauge_relative_eigenvalues"])
    fixed = "projected out" if "gauge_x" in r["projected_out"] else "kept (--keep-gauge)"
    typer.echo(f"body-frame gauge (rotate q and all P_i together; images unchanged): W~ on it {gauge}; {fixed}")
    com = " ".join(f"{v:.1e}" for v in r["com_shift_relative_eigenvalues"])
    typer.echo(f"centre-of-mass shift (all P_i by c, rho by -D c; images unchanged at t_0): W~ on it {com}")
    rel = r["relative_eigenvalues"]
    typer.echo(f"eigenvalues of W~ ({len(rel)}, ascending, relative): " + " ".join(f"{v:.2e}" for v in rel))
    cond = r["condition_number"]
    typer.echo(
        f"relative condition lambda_min/lambda_max = {r['relative_condition']:.2e}"
        + ("" if cond is not None else " (smallest eigenvalue at round-off)")
    )
    typer.echo(f"weakest {len(r['weak_directions'])} directions (unit vectors in scaled coordinates):")
    for d in r["weak_directions"]:
        comps = ", ".join(f"{k} {v:+.2f}" for k, v in d["components"].items())
        typer.echo(
            f"  {d['relative']:.2e}  {comps}   [k {d['k_share']:.2f}, com shift {d['com_shift_share']:.2f}, "
            f"gauge {d['gauge_share']:.2f}]"
        )
    typer.echo("CRLB sqrt(diag((W + P0^-1)^-1)) (SI: m, m/s, rad/s, -, m, -):")
    sig = r["crlb_sigma"]
    blocks = [names[0:3], names[3:6], names[6:9], names[9:13]]
    blocks += [names[13 + 3 * i : 16 + 3 * i] for i in range((len(names) - 15) // 3)] + [names[-2:]]
    for b in blocks:
        typer.echo("  " + "  ".join(f"{k} {sig[k]:.3e}" for k in b))
    rms = r["crlb_rms"]
    typer.echo(
        f"  RMS error bounds: rho {rms['rho_m']:.3g} m, rho_dot {rms['rho_dot_mps']:.3g} m/s, "
        f"omega {rms['omega_degps']:.3g} deg/s, theta {rms['theta_deg']:.3g} deg, k1 {rms['k1']:.3g}, k2 {rms['k2']:.3g}"
    )
    km = r["k_sigma_measurements_only"]
    typer.echo(f"  k from the measurements alone (no prior on k): k1 {km['k1']:.3g}, k2 {km['k2']:.3g}")


# --------------------------------------------------------------------------- inertia

UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}


def mesh_mass_properties(
    path: Path, density: float = 1000.0, units: str = "m", repair: bool = False
) -> tuple[dict[str, Any], list[str]]:
    """Read, check (optionally repair) a mesh and compute its mass properties in SI.

    Returns the JSON-ready dict and a list of problems (non-empty: the mesh cannot be used;
    the dict then holds only what was read and repaired).
    """
    from ..core import mesh as M
    from ..meshio import MeshFileError, read_mesh

    try:
        data = read_mesh(path)
    except MeshFileError as exc:
        return {}, [str(exc)]
    V = data.vertices * UNITS[units]
    F = data.faces
    changes: list[str] = []
    if repair:
        V, F, changes = M.repair_mesh(V, F)
    out: dict[str, Any] = {
        "mesh": str(path),
        "format": data.format,
        "units_in_file": units,
        "density": _num(density),
        "vertices": int(len(V)),
        "triangles": int(len(F)),
        "notes": list(data.notes),
        "repairs": changes,
    }
    chk = M.check_mesh(V, F)
    if chk.problems:
        prefix = f"{path}: "
        probs = [prefix + p for p in chk.problems]
        if repair and changes:
            probs.append(prefix + "after --repair, which " + "; ".join(changes))
        return out, probs
    mp = M.mass_properties(V, F, density)
    equal = M.equal_moment_pairs(mp.principal_moments)
    if equal:
        out["notes"].append(
            "equal principal moments "
            + ", ".join(f"{i + 1} and {j + 1}" for i, j in equal)
            + ": their axes are any orthonormal pair in their plane"
        )
    out.update(
        shells=len(chk.shells),
        volume=_num(mp.volume),
        mass=_num(mp.mass),
        centroid=_vec(mp.centroid),
        inertia=_mat(mp.inertia),
        principal_moments=_vec(mp.principal_moments),
        principal_axes=_mat(mp.principal_axes),
        k1=_num(mp.k1),
        k2=_num(mp.k2),
    )
    return out, []


def scenario_with_inertia(text: str, moments, comment: str | None = None) -> str:
    """``text`` (a scenario's YAML) with ``target.inertia_kgm2`` replaced by ``moments``.

    Only the characters of that value change (plus an optional comment line above the key
    when ``target`` is a block mapping): comments, order and formatting elsewhere are kept.
    """
    import yaml

    root = yaml.compose(text, Loader=yaml.SafeLoader)
    if not isinstance(root, yaml.MappingNode):
        raise ValueError("the scenario is not a YAML mapping")

    def child(node: yaml.Node, key: str) -> tuple[yaml.Node, yaml.Node]:
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.value == key:
                    return k, v
        raise ValueError(f"the scenario has no '{key}' mapping key")

    _, target = child(root, "target")
    key, value = child(target, "inertia_kgm2")
    start, end = value.start_mark.index, value.end_mark.index
    span = text[start:end]
    trailing = span[len(span.rstrip()) :]
    flow = "[" + ", ".join(repr(float(m)) for m in moments) + "]"
    new = text[:start] + flow + trailing + text[end:]
    if comment and isinstance(target, yaml.MappingNode) and not target.flow_style:
        line_start = new.rfind("\n", 0, key.start_mark.index) + 1
        indent = new[line_start : key.start_mark.index]
        if indent.strip() == "":
            new = new[:line_start] + f"{indent}# {comment}\n" + new[line_start:]
    return new


def _write_target_config(scenario: Path, out: Path, moments, comment: str) -> list[str]:
    """Write ``scenario`` with new ``target.inertia_kgm2`` to ``out``, validated before and after."""
    from ..config import ScenarioError, load_scenario, load_scenario_text

    try:
        text = scenario.read_text(encoding="utf-8")
        new = scenario_with_inertia(text, moments, comment)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        return [f"{scenario}: cannot update target.inertia_kgm2: {exc}"]
    try:
        load_scenario_text(new, str(out))
    except ScenarioError as exc:
        return [f"the updated scenario would be invalid: {p}" for p in exc.problems]
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(new, encoding="utf-8")
        load_scenario(out)
    except OSError as exc:
        return [f"{out}: cannot write: {exc}"]
    except ScenarioError as exc:  # pragma: no cover - the text was validated above
        out.unlink(missing_ok=True)
        return [str(p) for p in exc.problems]
    return []


def _print_inertia(r: dict[str, Any]) -> None:
    typer.echo(
        f"mesh: {r['mesh']} ({r['format']}, {r['vertices']} vertices, {r['triangles']} triangles, "
        f"{r['shells']} shell(s)); coordinates in {r['units_in_file']}, density {r['density']:g} kg/m^3"
    )
    for note in r["notes"]:
        typer.echo(f"note: {note}")
    for change in r["repairs"]:
        typer.echo(f"repair: {change}")
    typer.echo("all outputs in SI units (m, kg, kg m^2)")
    typer.echo(f"volume    {r['volume']:.9g} m^3")
    typer.echo(f"mass      {r['mass']:.9g} kg")
    typer.echo(f"centroid  {_fmt_vec(r['centroid'], '.9g')} m")
    typer.echo("inertia about the centroid, mesh axes (kg m^2):")
    for row in r["inertia"]:
        typer.echo("  " + _fmt_vec(row, "15.9g"))
    typer.echo("principal moments, ascending (kg m^2): " + _fmt_vec(r["principal_moments"], ".9g"))
    typer.echo("principal axes (columns, mesh axes):")
    for row in r["principal_axes"]:
        typer.echo("  " + _fmt_vec(row, "10.6f"))
    typer.echo(f"k1 = ln(I1/I2) = {r['k1']:.9g}    k2 = ln(I2/I3) = {r['k2']:.9g}")


INERTIA_HELP = (
    "Mass properties of a closed triangle mesh at constant density (divergence theorem, thesis ch. 7.4).\n\n"
    "Prints volume, mass, centroid, the inertia tensor about the centroid (mesh axes), principal moments "
    "(ascending) and axes (columns), and k1 = ln(I1/I2), k2 = ln(I2/I3).\n\n"
    "--units is the unit of the mesh file's coordinates; all outputs are SI (m, m^3, kg, kg m^2).\n\n"
    "A mesh that is open, non-manifold, inconsistently oriented, inward-facing or degenerate is an error "
    "(exit 2) unless --repair can fix it.\n\n"
    "With --target-config S --write-config OUT, OUT is a copy of S whose target.inertia_kgm2 holds the "
    "principal moments in ascending order (the target's x, y, z are the principal axes in that order)."
)


@app.command(help=INERTIA_HELP)
def inertia(
    mesh: Path = typer.Argument(..., help="closed triangle mesh: .obj, .stl (ASCII or binary), .ply (ASCII or binary)"),
    density: float = typer.Option(
        1000.0, "--density", help="constant density in kg/m^3 (default 1000 = 1 g/cm^3, as in the thesis)"
    ),
    units: str = typer.Option(
        "m", "--units", help="unit of the mesh file's coordinates: m, cm or mm. Outputs are always SI (m, kg, kg m^2)."
    ),
    repair: bool = typer.Option(
        False,
        "--repair",
        help="fix what can be fixed and say what changed: merge duplicate vertices, drop degenerate/duplicate "
        "triangles, flip faces to a consistent orientation, flip inward-facing shells (holes are not filled)",
    ),
    as_json: bool = typer.Option(False, "--json", help="print one JSON object (SI units)"),
    target_config: Optional[Path] = typer.Option(
        None,
        "--target-config",
        help="scenario whose target.inertia_kgm2 gets the principal moments (needs --write-config)",
    ),
    write_config: Optional[Path] = typer.Option(
        None, "--write-config", help="new scenario file to write (never the --target-config file itself)"
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="allow --write-config to replace an existing file"),
) -> None:
    """Mass properties of a closed triangle mesh (see INERTIA_HELP)."""
    problems: list[str] = []
    if units not in UNITS:
        problems.append(f"--units must be m, cm or mm (got {units!r})")
    if not (math.isfinite(density) and density > 0):
        problems.append(f"--density must be a positive number of kg/m^3 (got {density})")
    if (target_config is None) != (write_config is None):
        problems.append("--target-config and --write-config go together (the scenario is never edited in place)")
    if target_config is not None and write_config is not None:
        load_or_exit(target_config)
        if write_config.exists() and os.path.samefile(write_config, target_config):
            problems.append(f"--write-config {write_config} is the --target-config file: write to a new file")
        elif write_config.exists() and not overwrite:
            problems.append(f"{write_config} exists (use --overwrite to replace it)")
        elif write_config.is_dir():
            problems.append(f"{write_config} is a directory")
    if problems:
        fail(problems)

    r, problems = mesh_mass_properties(mesh, density, units, repair)
    if problems:
        fail(problems)
    if target_config is not None and write_config is not None:
        comment = (
            f"inertia_kgm2 written by 'spmc inertia {mesh.name}' ({density:g} kg/m^3, mesh in {units}): "
            "principal moments, ascending"
        )
        problems = _write_target_config(target_config, write_config, r["principal_moments"], comment)
        if problems:
            fail(problems)
        r["written_config"] = str(write_config)
    if as_json:
        _echo_json(r)
    else:
        _print_inertia(r)
        if "written_config" in r:
            typer.echo(f"wrote {write_config}: target.inertia_kgm2 = {_fmt_vec(r['principal_moments'], '.9g')}")
