"""Regenerate the key tables of docs/scenarios.md from the pydantic schema.

    .venv/bin/python docs/make_scenario_table.py          # rewrite the tables in place
    .venv/bin/python docs/make_scenario_table.py --print  # print them

Types, constraints and defaults come from ``stereopose_mc.config.schema``; units from
the key's suffix; meanings from ``MEANINGS`` below (or the field's ``description``).
Only the text between the ``<!-- keys:begin -->`` and ``<!-- keys:end -->`` markers is
replaced; the rest of docs/scenarios.md is written by hand.
"""

from __future__ import annotations

import sys
import typing
from pathlib import Path
from typing import Any

import annotated_types as at
from pydantic import BaseModel
from pydantic.fields import FieldInfo

from stereopose_mc.config.schema import EKFConfig, IEKFConfig, MEKFConfig, Scenario, UKFConfig

DOC = Path(__file__).resolve().parent / "scenarios.md"
BEGIN, END = "<!-- keys:begin -->", "<!-- keys:end -->"

# Units by key suffix (longest first). The numerical core gets SI (m, s, rad); degrees are converted on load.
UNITS = [
    ("_deg2ps2", "deg²/s²"), ("_m2ps2", "m²/s²"), ("_radps2", "rad/s²"), ("_kgm2", "kg m²"), ("_degps", "deg/s"),
    ("_mps", "m/s"), ("_deg", "deg"), ("_km", "km"), ("_m2", "m²"), ("_s", "s"), ("_m", "m"),
]  # fmt: skip
UNIT_BY_KEY = {
    "image_sigma": "normalized image units (focal length 1)",
    "flow_sigma": "normalized image units / s",
    "disparity_sigma": "normalized image units",
    "focal_length": "normalized (1 = image coordinates are x/y, z/y)",
    "q": "–",
    "k": "–",
    "e": "–",
}

MEANINGS = {
    "name": "Scenario name: run directories (`runs/<name>`), output metadata.",
    "description": "Free text, copied into the outputs.",
    "seed": "Root seed. Trial `j` draws from `SeedSequence(seed, spawn_key=(j,))`: initial-estimate error, image noise, "
            "angular-acceleration noise, in that order.",
    "trials": "Number of Monte Carlo trials (`spmc run --trials` overrides).",
    "time.dt_s": "Measurement and filter step Δt; the first update is at t = Δt (none at t = 0).",
    "time.duration_s": "Simulated time; must be a whole number of `dt_s`.",
    "time.error_window_start_s": "Per-trial mean errors are taken over t ≥ this (thesis: 10 s); must be < `duration_s`.",
    "time.truth_rtol": "Relative tolerance of the DOP853 integration of the truth.",
    "leader.orbit.a_km": "Leader semi-major axis. The perigee a(1 − e) must be above the Earth's surface (6378.137 km).",
    "leader.orbit.e": "Leader eccentricity.",
    "leader.orbit.i_deg": "Inclination. Only a, e and ν(0) enter the relative dynamics in L; i, Ω, ω are recorded "
                          "for completeness.",
    "leader.orbit.raan_deg": "Right ascension of the ascending node (as `i_deg`).",
    "leader.orbit.argp_deg": "Argument of perigee (as `i_deg`).",
    "leader.orbit.true_anomaly_deg": "Leader true anomaly ν at t = 0 (the thesis does not state it; we use 0).",
    "target.inertia_kgm2": "True principal moments [Ix, Iy, Iz] of the target, each > 0, obeying the triangle "
                           "inequality. Only the ratios k1 = ln(Ix/Iy), k2 = ln(Iy/Iz) enter the state.",
    "target.feature_points_m": "Feature points P_i in the target frame (relative to its centre of mass), one [x, y, z] "
                               "per point. Each must be in front of the cameras (y > 0 in L) at t = 0.",
    "truth_initial_state.rho_m": "ρ₀(0): target centre of mass in the leader's LVLH frame L (x radial, y along-track, "
                                 "z orbit normal). The cameras look along +y.",
    "truth_initial_state.rho_dot_mps": "ρ̇₀(0), in L.",
    "truth_initial_state.omega_degps": "ω(0): angular velocity of the target relative to L, components in L.",
    "truth_initial_state.q": "q(0): Hamilton quaternion, scalar first, target → leader (v^L = D(q) v^T); must be "
                             "non-zero; normalized on load.",
    "camera.baseline_m": "Stereo baseline b: right camera at the leader's centre of mass, left camera at +b along x.",
    "camera.focal_length": "Focal length; every image channel scales with it.",
    "measurements.image_sigma": "Truth noise σ on u_R, v_R, u_L, v_L (thesis: 1e-5). 0 = noise-free (then every filter "
                                "must set its own `measurement_noise.image_sigma`).",
    "measurements.flow_sigma": "Truth noise σ on the image velocities u̇_R, v̇_R, u̇_L, v̇_L (thesis: 1e-5). 0 as above.",
    "measurements.disparity": "Add the disparity channel d = u_L − u_R = −b/y per feature.",
    "measurements.disparity_sigma": "Truth noise σ on d; null = √2 · `image_sigma` (the difference of two independent "
                                    "channels).",
    "measurements.inertia_pseudo_measurement.enabled": "Append the 3-row inertia pseudo-measurement (Euler's equation, "
                                                       "observed value 0; thesis 6.2.2). Off in cases E and F.",
    "measurements.inertia_pseudo_measurement.angular_acceleration_sigma_radps2": "σ_α of the Gaussian noise on the "
        "measured relative angular acceleration α (thesis: not stated; we use 1e-6). Must be > 0: the "
        "pseudo-measurement's R is built from it.",
    "measurements.inertia_pseudo_measurement.angular_acceleration": "How α is obtained: the true ω̇ plus noise (the "
                                                                    "thesis's assumption; the thesis's shortcut; see docs/angular-acceleration.md for the differentiated sources).",
    "initial_covariance.rho_m2": "P₀ variance of each component of ρ₀; the initial estimate is drawn from "
                                 "N(x_true(0), P₀).",
    "initial_covariance.rho_dot_m2ps2": "P₀ variance of each component of ρ̇₀.",
    "initial_covariance.omega_deg2ps2": "P₀ variance of each component of ω (converted to rad²/s²).",
    "initial_covariance.q": "P₀ variance of each quaternion component (the draw is renormalized).",
    "initial_covariance.feature_points_m2": "P₀ variance of each feature-point coordinate.",
    "initial_covariance.k": "P₀ variance of k1 and of k2.",
    "filters": "The filters run on every trial (same initial estimate and measurements: paired errors). Entries: see "
               "the next table. Default: one IEKF with all defaults.",
    "percentiles": "Percentiles of the per-trial mean errors in the summary tables (thesis: 50, 70, 90, 100).",
    "divergence.rho_m": "A trial whose position error exceeds this is flagged `inconsistent` (a flag: it runs on and its "
                         "errors count; docs/filters.md).",
    "divergence.rho_dot_mps": "Same for the velocity error.",
    "divergence.omega_degps": "Same for the angular-velocity error.",
    "divergence.k": "Same for the error of k1 or k2.",
    "divergence.nis_window_steps": "Steps over which the NIS is averaged for the lost-filter test.",
    "divergence.nis_start_s": "Time from which the lost-filter (NIS) test applies; the first updates are far from linear.",
    "dispersions": "Truth dispersions: `sampling` (`random` \\| `sobol` \\| `lhs`) and one entry per dispersed key path "
    "(`{dist: ..., mode: ..., applies_to: ...}`); null = every trial shares the nominal truth. See \"Dispersions\" below.",
    "divergence.sigma_ratio": "A trial is flagged `inconsistent` when a block's error stays above this many of "
                              "the filter's own sigmas for that block over `nis_window_steps` steps (docs/filters.md).",
    "divergence.nees_factor": "A trial is `inconsistent` when its gauge-projected NEES stays above this times the "
                              "chi-square 99.9 % bound over `nis_window_steps` steps (docs/filters.md).",
}  # fmt: skip

FILTER_MEANINGS = {
    "type": "`iekf` (iterated EKF, Gauss-Newton form), `ekf`, `mekf` (multiplicative EKF) or `ukf` (unscented, "
            "multiplicative attitude). See docs/filters.md.",
    "name": "Label in the outputs; default the type. Labels must be unique within `filters`.",
    "measurement_noise.image_sigma": "The filter's R: σ for u, v. null = the truth's `measurements.image_sigma` (which "
                                     "must then be > 0).",
    "measurement_noise.flow_sigma": "The filter's R: σ for the image velocities. null = the truth's.",
    "measurement_noise.disparity_sigma": "The filter's R: σ for d. null = the truth's.",
    "measurement_noise.angular_acceleration_sigma_radps2": "The filter's σ_α for the pseudo-measurement. null = the "
                                                           "truth's.",
    "process_noise.rho_m2": "The filter's Q: variance added per step to each ρ₀ component (derivation: docs/filters.md).",
    "process_noise.rho_dot_m2ps2": "Q per step, each ρ̇₀ component.",
    "process_noise.omega_deg2ps2": "Q per step, each ω component.",
    "process_noise.q": "Q per step, each quaternion component.",
    "process_noise.feature_points_m2": "Q per step, each feature-point coordinate.",
    "process_noise.k": "Q per step, k1 and k2.",
    "transition": "Φ = expm(F Δt) exactly (`expm`) or by its Taylor series (`taylor`).",
    "taylor_order": "Order of the Taylor series of Φ.",
    "integration_substeps": "RK4 substeps per Δt in the prediction.",
    "iterated": "MEKF: run the IEKF's Gauss-Newton iterations (with `tolerance`, `max_iterations`, `step_control`, "
                "`stopping`) in every update; false (default): plain EKF updates on the error state, the classical "
                "MEKF (docs/filters.md, which combination is which).",
    "alpha": "UKF sigma-point spread α (van der Merwe scaling).",
    "beta": "UKF prior-distribution parameter β (2 for a Gaussian).",
    "kappa": "UKF secondary scaling κ.",
    "first_update": "EKF / UKF: `iterated` runs the IEKF's iterations at the first update (t = Δt), plain EKF "
                    "updates after; `ekf` (default) keeps every update plain. See docs/filters.md.",
    "tolerance": "IEKF stopping tolerance on the (unit-free) increment size (thesis: 0.01).",
    "max_iterations": "IEKF iteration limit (thesis: 10).",
    "step_control": "IEKF step control: backtracking line search on the MAP cost, Levenberg-Marquardt damping, or "
                    "`none` (the thesis's plain iteration). See docs/filters.md.",
    "stopping": "IEKF stopping test: increment in posterior (`mahalanobis`) or prior (`prior`) standard deviations, "
                "scaled by sqrt(diag P) (`scaled`), or the raw norm (`raw`, the thesis's). See docs/filters.md.",
}  # fmt: skip


def _fmt_num(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(int(v)) if v.is_integer() and abs(v) < 1e6 else f"{v:g}"
    return str(v)


def _fmt_value(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt_value(x) for x in v) + "]"
    if isinstance(v, str):
        return v if v else '""'
    return _fmt_num(v)


def _constraints(meta: list[Any]) -> tuple[str, str]:
    """(number bounds like '> 0', list length like '3') from annotated_types metadata."""
    bounds, length = [], {}
    for m in meta:
        if isinstance(m, at.Gt):
            bounds.append(f"> {_fmt_num(m.gt)}")
        elif isinstance(m, at.Ge):
            bounds.append(f"≥ {_fmt_num(m.ge)}")
        elif isinstance(m, at.Lt):
            bounds.append(f"< {_fmt_num(m.lt)}")
        elif isinstance(m, at.Le):
            bounds.append(f"≤ {_fmt_num(m.le)}")
        elif isinstance(m, at.MinLen):
            length["min"] = m.min_length
        elif isinstance(m, at.MaxLen):
            length["max"] = m.max_length
        elif getattr(m, "pattern", None):
            bounds.append(f"matching `{m.pattern.strip('^$')}`")
    if length.get("min") is not None and length.get("min") == length.get("max"):
        n = str(length["min"])
    elif "min" in length:
        n = f"≥ {length['min']}"
    else:
        n = ""
    return ", ".join(bounds), n


def fmt_type(tp: Any, meta: list[Any] | None = None) -> str:
    """A short human description of a schema type, e.g. 'list of 3 float > 0'."""
    meta = list(meta or [])
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        inner, *extra = typing.get_args(tp)
        more = [x for e in extra for x in (e.metadata if isinstance(e, FieldInfo) else [e])]
        return fmt_type(inner, meta + more)
    bounds, n = _constraints(meta)
    args = typing.get_args(tp)
    if origin is typing.Literal:
        return " \\| ".join(f"`{a}`" for a in args)
    if origin in (typing.Union,) or type(tp).__name__ == "UnionType":
        parts = [fmt_type(a, meta) for a in args if a is not type(None)]
        return " or ".join(parts) + (" or null" if type(None) in args else "")
    if origin is list:
        return f"list{f' ({n})' if n else ''} of {fmt_type(args[0])}"
    name = getattr(tp, "__name__", str(tp))
    return f"{name} {bounds}".strip()


def unit_of(key: str) -> str:
    leaf = key.split(".")[-1]
    if leaf in UNIT_BY_KEY:
        return UNIT_BY_KEY[leaf]
    for suffix, unit in UNITS:
        if leaf.endswith(suffix):
            return unit
    return ""


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def leaves(model: type[BaseModel], prefix: str = "") -> list[tuple[str, FieldInfo, type[BaseModel]]]:
    """Every leaf key of ``model`` (nested models flattened to dotted paths)."""
    out = []
    for name, f in model.model_fields.items():
        key = prefix + name
        if _is_model(f.annotation):
            out += leaves(f.annotation, key + ".")
        else:
            out.append((key, f, model))
    return out


def _default(f: FieldInfo) -> str:
    if f.is_required():
        return "**required**"
    if f.default_factory is not None:
        return "see meaning"
    return f"`{_fmt_value(f.default)}`"


def scenario_rows() -> list[tuple[str, str, str, str, str]]:
    rows = []
    for key, f, _ in leaves(Scenario):
        meaning = MEANINGS.get(key) or f.description or ""
        rows.append((key, fmt_type(f.annotation, f.metadata) if key != "filters" else "list (≥ 1) of filter entries",
                     unit_of(key), _default(f), meaning))  # fmt: skip
    return rows


def filter_rows() -> list[tuple[str, str, str, str, str, str]]:
    models = {"iekf": IEKFConfig, "ekf": EKFConfig, "mekf": MEKFConfig, "ukf": UKFConfig}
    fields = {t: {k: f for k, f, _ in leaves(m)} for t, m in models.items()}
    order = ["type"]
    for t in models:
        order += [k for k in fields[t] if k not in order]
    rows = []
    for key in order:
        types = [t for t in models if key in fields[t]]
        f = fields[types[0]][key]
        applies = "all" if len(types) == len(models) else ", ".join(types)
        typ = " \\| ".join(f"`{t}`" for t in models) if key == "type" else fmt_type(f.annotation, f.metadata)
        default = " / ".join(f"{t}: {_default(fields[t][key])}" for t in types) if len(
            {_default(fields[t][key]) for t in types}) > 1 else _default(f)  # fmt: skip
        meaning = FILTER_MEANINGS.get(key) or f.description or ""
        rows.append((key, applies, typ, unit_of(key), default, meaning))
    return rows


def key_paths() -> list[str]:
    """Every documented key: scenario leaves, and ``filters[].KEY`` for filter entries."""
    return [r[0] for r in scenario_rows()] + [f"filters[].{r[0]}" for r in filter_rows()]


def render() -> str:
    out = ["### Scenario keys", "", "| key | type | unit | default | meaning |", "|---|---|---|---|---|"]
    out += [f"| `{k}` | {t} | {u} | {d} | {m} |" for k, t, u, d, m in scenario_rows()]
    out += ["", "### Filter entries (`filters[]`)", "",
            "| key | filter | type | unit | default | meaning |", "|---|---|---|---|---|---|"]  # fmt: skip
    out += [f"| `filters[].{k}` | {a} | {t} | {u} | {d} | {m} |" for k, a, t, u, d, m in filter_rows()]
    missing = [r[0] for r in scenario_rows() + filter_rows() if not r[-1]]
    if missing:
        print(f"warning: no meaning written for {missing}", file=sys.stderr)
    return "\n".join(out)


def main(argv: list[str]) -> None:
    table = render()
    if "--print" in argv:
        print(table)
        return
    text = DOC.read_text(encoding="utf-8")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    DOC.write_text(f"{head}{BEGIN}\n{table}\n{END}{tail}", encoding="utf-8")
    print(f"wrote {DOC}")


if __name__ == "__main__":
    main(sys.argv[1:])
