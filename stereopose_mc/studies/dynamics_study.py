"""The dynamical-model studies of thesis section 2.5 (figures 2.3-2.10), as figures and tables.

Three studies on one scenario (its leader orbit, initial relative state, inertia and
feature points):

(a) **Nonlinear vs Clohessy-Wiltshire** (figs 2.5-2.7). The c.m.'s initial relative state
    ``[rho_0, rho_0']`` is propagated with the nonlinear model of docs/model.md (DOP853) and with
    the closed-form CW solution at ``n = sqrt(mu / a^3)`` (thesis eq. 2.31), on a circular
    orbit (the scenario's ``a`` with ``e = 0``) and on the scenario's (eccentric) orbit.
    On the circular orbit the difference is the CW linearization error, quadratic in the
    separation: the exponent is fitted from the whole relative state scaled by
    ``scaling_factors``. A docking case (fig 2.7): the CW initial velocity that brings the
    c.m. to the leader at ``dock_time_s`` (:func:`cw.cw_intercept_velocity`); the feature
    points, ``rho_i = rho_CW + D P_i``, cross ``y = 0`` at other times.
(b) **Simplified vs coupled feature model** (figs 2.3-2.4): feature positions
    ``rho_0 + D P_i`` of the simplified model against the Segal-Gurfil model's integrated
    ``rho_i`` (:mod:`.coupled`), both DOP853 at ``rtol``. Their difference is compared with
    the integration error (the simplified model at ``rtol`` against ``rtol_reference``), and
    with the coupled model as printed in the thesis (sign misprints kept).
(c) **Cost vs number of feature points** (figs 2.8-2.10): wall time to propagate both models
    over ``timing_duration_s`` (default the scenario's duration) for ``N`` points on a
    sphere of the scenario's mean feature radius, with fixed-step RK4 at the scenario's
    ``dt`` (the filter's integrator) and with adaptive DOP853 (``timing_rtol``, like the
    thesis's ode45). The simplified model's time includes forming ``rho_0 + D P_i`` at the
    output times. ``v% = (t_coupled - t_simplified) / t_coupled`` (thesis eq. 2.47, from the CPU
    times: on an idle machine they equal the wall times of this single-threaded code). The
    shortest of ``timing_repeats`` interleaved runs is reported, as wall time (``t_*``) and as
    process CPU time (``cpu_*``, insensitive to other load on the machine).

Outputs (:func:`write_outputs`): PNG (150 dpi) and SVG figures, ``dynamics.csv`` (long
format: study, case, quantity, value, unit), ``timing.csv`` (wide), ``dynamics.md`` and
``manifest.json``.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.integrate import solve_ivp

from ..config.resolve import setup_of
from ..config.schema import Scenario
from ..core import state as st
from ..core.dynamics import translational_acceleration
from ..core.orbit import Orbit, leader_kinematics
from ..rundir import store
from . import coupled as cp
from .cw import cw_intercept_velocity, cw_propagate
from .figure_files import save_figure

Array = NDArray[np.float64]
TIMING_POINTS = (1, 5, 10, 20, 50, 100)


@dataclass(frozen=True)
class StudyOptions:
    """Knobs of the three studies (SI units)."""

    horizon_s: float | None = None  # (a), (b): default one leader orbital period
    samples: int = 1201  # output times over the horizon
    rtol: float = 1e-11
    rtol_reference: float = 1e-13
    scaling_factors: tuple[float, ...] = (0.5, 1.0, 2.0)
    dock_time_s: float = 80.0
    timing_points: tuple[int, ...] = TIMING_POINTS
    timing_repeats: int = 5
    timing_duration_s: float | None = None  # (c): default the scenario's duration
    timing_rtol: float = 1e-9


# ----------------------------------------------------------------------------- integration


Rhs = Callable[..., Array]


def integrate(rhs: Rhs, y0: Array, t: Array, orbit: Orbit, rtol: float, **kw) -> tuple[Array, int]:
    """DOP853 integration of ``y' = rhs(y, r_L, nu', nu'', **kw)`` sampled at ``t``; ``(Y (T, n), nfev)``.

    ``atol = 1e-3 rtol`` on every component (metres, m/s, rad/s and the quaternion are all
    far above it); the leader's kinematics come from Kepler's equation at each call.
    """

    def f(tt: float, y: Array) -> Array:
        lk = leader_kinematics(orbit, tt)
        return rhs(y, lk.r, lk.nu_dot, lk.nu_ddot, **kw)

    sol = solve_ivp(f, (t[0], t[-1]), y0, method="DOP853", t_eval=t, rtol=rtol, atol=1e-3 * rtol)
    if not sol.success:  # pragma: no cover - smooth problem
        raise RuntimeError(f"integration failed: {sol.message}")
    return sol.y.T, int(sol.nfev)


def translation_rhs(y: Array, r_L, nu_dot, nu_ddot, mu: float) -> Array:
    """``[rho', g(rho, rho')]`` of the nonlinear c.m. model (docs/model.md)."""
    acc = translational_acceleration(y[..., :3], y[..., 3:], r_L, nu_dot, nu_ddot, mu)
    return np.concatenate([y[..., 3:], acc], axis=-1)


def circular_twin(orbit: Orbit) -> Orbit:
    """The scenario's orbit with ``e = 0`` (same ``a``, orientation and initial anomaly)."""
    return Orbit(a=orbit.a, e=0.0, i=orbit.i, raan=orbit.raan, argp=orbit.argp, nu0=orbit.nu0, mu=orbit.mu)


# ----------------------------------------------------------------------------- (a) CW


@dataclass(frozen=True)
class CWCase:
    name: str  # "circular" | "eccentric"
    orbit: Orbit
    t: Array
    nonlinear: Array  # (T, 6)
    cw: Array  # (T, 6)

    @property
    def difference(self) -> Array:
        """``|rho_NL - rho_CW|`` (T,)."""
        return np.linalg.norm(self.nonlinear[:, :3] - self.cw[:, :3], axis=-1)


def cw_case(name: str, orbit: Orbit, s0: Array, t: Array, rtol: float) -> CWCase:
    """Nonlinear and CW propagation of the c.m. state ``s0 = [rho, rho']`` over ``t``."""
    nl, _ = integrate(translation_rhs, s0, t, orbit, rtol, mu=orbit.mu)
    return CWCase(name, orbit, t, nl, cw_propagate(s0, orbit.mean_motion, t))


def scaling_study(
    orbit: Orbit, s0: Array, t: Array, factors: tuple[float, ...], rtol: float
) -> tuple[Array, Array, float]:
    """``max_t |rho_NL - rho_CW|`` for ``s0`` scaled by each factor, and the log-log slope (expect 2)."""
    f = np.asarray(factors, dtype=float)
    d = np.array([cw_case("scaled", orbit, c * s0, t, rtol).difference.max() for c in f])
    slope = float(np.polyfit(np.log(f), np.log(d), 1)[0]) if f.size > 1 else float("nan")
    return f, d, slope


@dataclass(frozen=True)
class Docking:
    t: Array
    v0: Array  # CW intercept velocity (3,)
    cm_cw: Array  # (T, 3)
    cm_nl: Array  # (T, 3)
    features_cw: Array  # (T, N, 3): rho_CW + D P_i

    def y_crossings(self) -> Array:
        """First time ``y = 0`` is reached from above, c.m. (CW) then each point (nan if never)."""
        ys = np.concatenate([self.cm_cw[:, None, 1], self.features_cw[..., 1]], axis=1)
        return np.array([first_crossing(self.t, ys[:, j]) for j in range(ys.shape[1])])


def first_crossing(t: Array, y: Array) -> float:
    """First ``t`` with ``y(t) = 0`` after starting positive, by linear interpolation."""
    idx = np.flatnonzero((y[:-1] > 0.0) & (y[1:] <= 0.0))
    if idx.size == 0:
        return float("nan")
    j = idx[0]
    return float(t[j] + (t[j + 1] - t[j]) * y[j] / (y[j] - y[j + 1]))


def docking_study(orbit: Orbit, s0: Array, k: Array, t_dock: float, rtol: float, samples: int = 1201) -> Docking:
    """Fig. 2.7: CW intercept at ``t_dock`` on ``orbit`` (circular); points from the attitude ODE."""
    n = orbit.mean_motion
    v0 = cw_intercept_velocity(s0[cp.RHO], n, t_dock)
    s = s0.copy()
    s[cp.RHO_DOT] = v0
    t = np.linspace(0.0, 1.5 * t_dock, samples)
    Y, _ = integrate(cp.simplified_rhs, s, t, orbit, rtol, k=k, mu=orbit.mu)
    cm_cw = cw_propagate(s[:6], n, t)[:, :3]
    N = cp.n_points_simplified(s.size)
    return Docking(t, v0, cm_cw, Y[:, cp.RHO], cm_cw[:, None, :] + cp.points_in_L(Y, N))


# ----------------------------------------------------------------------------- (b) coupled


@dataclass(frozen=True)
class FeatureStudy:
    t: Array
    cm: Array  # (T, 3) c.m. of the simplified model
    simplified: Array  # (T, N, 3)
    coupled: Array  # (T, N, 3)
    as_printed: Array  # (T, N, 3) coupled model with the thesis's sign misprints
    reference: Array  # (T, N, 3) simplified at rtol_reference
    nfev_simplified: int
    nfev_coupled: int

    @property
    def difference(self) -> Array:
        """``|rho_i,coupled - rho_i,simplified|`` (T, N)."""
        return np.linalg.norm(self.coupled - self.simplified, axis=-1)

    @property
    def integration_error(self) -> Array:
        """``|rho_i,simplified(rtol) - rho_i,simplified(rtol_reference)|`` (T, N)."""
        return np.linalg.norm(self.simplified - self.reference, axis=-1)

    @property
    def printed_difference(self) -> Array:
        return np.linalg.norm(self.as_printed - self.simplified, axis=-1)


def feature_study(orbit: Orbit, s0: Array, k: Array, t: Array, rtol: float, rtol_reference: float) -> FeatureStudy:
    """Integrate the simplified and the coupled model from the same initial state ``s0 (13+3N)``."""
    c0 = cp.coupled_initial(s0)
    S, nfs = integrate(cp.simplified_rhs, s0, t, orbit, rtol, k=k, mu=orbit.mu)
    C, nfc = integrate(cp.coupled_rhs, c0, t, orbit, rtol, k=k, mu=orbit.mu)
    Cp, _ = integrate(cp.coupled_rhs, c0, t, orbit, rtol, k=k, mu=orbit.mu, as_printed=True)
    R, _ = integrate(cp.simplified_rhs, s0, t, orbit, rtol_reference, k=k, mu=orbit.mu)
    return FeatureStudy(
        t, S[:, cp.RHO], cp.simplified_features(S), cp.coupled_features(C), cp.coupled_features(Cp),
        cp.simplified_features(R), nfs, nfc,
    )


# ----------------------------------------------------------------------------- (c) timing


def sphere_points(n: int, radius: float) -> Array:
    """``n`` points spread over a sphere of ``radius`` (Fibonacci lattice), ``(n, 3)``."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return radius * np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def rk4_fixed(rhs: Rhs, y0: Array, t: Array, orbit: Orbit, **kw) -> Array:
    """Classical RK4 on the grid ``t`` (one step per interval), states at every grid time ``(T, n)``.

    The leader's kinematics at the stage times are computed once, before the loop.
    """
    h = np.diff(t)
    lk0, lkh = leader_kinematics(orbit, t), leader_kinematics(orbit, t[:-1] + 0.5 * h)
    Y = np.empty((t.size, y0.size))
    Y[0] = y = y0
    for j in range(h.size):
        a = (lk0.r[j], lk0.nu_dot[j], lk0.nu_ddot[j])
        m = (lkh.r[j], lkh.nu_dot[j], lkh.nu_ddot[j])
        b = (lk0.r[j + 1], lk0.nu_dot[j + 1], lk0.nu_ddot[j + 1])
        k1 = rhs(y, *a, **kw)
        k2 = rhs(y + 0.5 * h[j] * k1, *m, **kw)
        k3 = rhs(y + 0.5 * h[j] * k2, *m, **kw)
        k4 = rhs(y + h[j] * k3, *b, **kw)
        y = y + (h[j] / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        Y[j + 1] = y
    return Y


def best_times(runs: dict[str, Callable[[], object]], repeats: int) -> dict[str, tuple[float, float]]:
    """``{name: (wall, cpu)}``: the shortest wall-clock and process-CPU time of ``repeats`` runs each.

    Every run is called once untimed (warm-up); the timed runs are interleaved (run 1 of every
    function, then run 2, ...) so that load from other processes hits all of them alike, and
    the minimum is kept (the least disturbed run, as ``timeit`` recommends).
    """
    for fn in runs.values():
        fn()
    wall = {k: np.inf for k in runs}
    cpu = {k: np.inf for k in runs}
    for _ in range(repeats):
        for name, fn in runs.items():
            c0, w0 = time.process_time(), time.perf_counter()
            fn()
            wall[name] = min(wall[name], time.perf_counter() - w0)
            cpu[name] = min(cpu[name], time.process_time() - c0)
    return {k: (float(wall[k]), float(cpu[k])) for k in runs}


def timing_study(
    orbit: Orbit, base: Array, k: Array, radius: float, points: tuple[int, ...], duration: float, dt: float,
    repeats: int, rtol: float,
) -> pd.DataFrame:
    """Wall (``t_*``) and CPU (``cpu_*``) time of both models vs ``N`` (module docstring, study c).

    One row per ``N``; ``base`` is the 13-entry ``[rho_0, rho_0', w, q]``; timing by
    :func:`best_times`; ``v_*_pct`` (thesis eq. 2.47) from the CPU times.
    """
    t = np.linspace(0.0, duration, int(round(duration / dt)) + 1)
    rows = []
    for N in points:
        s0 = np.concatenate([base, sphere_points(N, radius).ravel()])
        c0 = cp.coupled_initial(s0)
        kw = dict(k=k, mu=orbit.mu)
        runs = {
            "rk4_simplified": lambda: cp.simplified_features(rk4_fixed(cp.simplified_rhs, s0, t, orbit, **kw)),
            "rk4_coupled": lambda: cp.coupled_features(rk4_fixed(cp.coupled_rhs, c0, t, orbit, **kw)),
            "dop853_simplified": lambda: cp.simplified_features(
                integrate(cp.simplified_rhs, s0, t, orbit, rtol, **kw)[0]
            ),
            "dop853_coupled": lambda: cp.coupled_features(integrate(cp.coupled_rhs, c0, t, orbit, rtol, **kw)[0]),
        }
        row: dict[str, float | int] = {"N": N, "n_simplified": s0.size, "n_coupled": c0.size}
        times = best_times(runs, repeats)
        for name, (wall, _) in times.items():
            row[f"t_{name}_s"] = wall
        for name, (_, cpu) in times.items():
            row[f"cpu_{name}_s"] = cpu
        row["nfev_dop853_simplified"] = integrate(cp.simplified_rhs, s0, t, orbit, rtol, **kw)[1]
        row["nfev_dop853_coupled"] = integrate(cp.coupled_rhs, c0, t, orbit, rtol, **kw)[1]
        for m in ("rk4", "dop853"):
            tc, ts = row[f"cpu_{m}_coupled_s"], row[f"cpu_{m}_simplified_s"]
            row[f"v_{m}_pct"] = 100.0 * (tc - ts) / tc
        rows.append(row)
    return pd.DataFrame(rows)


# ----------------------------------------------------------------------------- all studies


@dataclass
class DynamicsResult:
    scenario: str
    options: StudyOptions
    horizon: float
    cw_cases: list[CWCase]
    scaling: tuple[Array, Array, float]
    docking: Docking
    features: FeatureStudy
    timing: pd.DataFrame
    scenario_duration: float
    files: list[Path] = field(default_factory=list)


def run_studies(scn: Scenario, options: StudyOptions = StudyOptions()) -> DynamicsResult:
    """Run studies (a)-(c) on a scenario (no I/O)."""
    setup = setup_of(scn)
    orbit = setup.orbit
    N = setup.n_points
    x0 = setup.x0
    k = x0[st.k_slice(N)]
    s0 = x0[: cp.simplified_size(N)]
    duration = setup.dt * setup.steps
    horizon = options.horizon_s if options.horizon_s is not None else 2.0 * np.pi / orbit.mean_motion
    t = np.linspace(0.0, horizon, options.samples)
    if 0.0 < duration < horizon:  # sample the scenario's end exactly for the "within duration" numbers
        t = np.union1d(t, [duration])
    circ = circular_twin(orbit)
    cases = [cw_case("circular", circ, s0[:6], t, options.rtol), cw_case("eccentric", orbit, s0[:6], t, options.rtol)]
    scaling = scaling_study(circ, s0[:6], t, options.scaling_factors, options.rtol)
    dock = docking_study(circ, s0, k, options.dock_time_s, options.rtol)
    feats = feature_study(orbit, s0, k, t, options.rtol, options.rtol_reference)
    pts = st.points(x0)
    radius = float(np.mean(np.linalg.norm(pts, axis=-1))) if N else 1.0
    tdur = options.timing_duration_s if options.timing_duration_s is not None else duration
    timing = timing_study(
        orbit, s0[:13], k, radius, tuple(options.timing_points), tdur, setup.dt, options.timing_repeats,
        options.timing_rtol,
    )
    return DynamicsResult(scn.name, options, float(horizon), cases, scaling, dock, feats, timing, duration)


def summary_frame(r: DynamicsResult) -> pd.DataFrame:
    """The long-format summary table ``dynamics.csv``: study, case, quantity, value, unit."""
    rows: list[tuple[str, str, str, float, str]] = []
    for c in r.cw_cases:
        d = c.difference
        in_dur = c.t <= r.scenario_duration + 1e-9
        rows += [
            ("nl_vs_cw", c.name, "max_position_difference", float(d.max()), "m"),
            ("nl_vs_cw", c.name, "time_of_max_difference", float(c.t[np.argmax(d)]), "s"),
            ("nl_vs_cw", c.name, "max_position_difference_within_scenario_duration", float(d[in_dur].max()), "m"),
            ("nl_vs_cw", c.name, "final_position_difference", float(d[-1]), "m"),
            ("nl_vs_cw", c.name, "horizon", float(c.t[-1]), "s"),
        ]
    f, dmax, slope = r.scaling
    for fi, di in zip(f, dmax):
        rows.append(("nl_vs_cw_scaling", "circular", f"max_position_difference_x{fi:g}", float(di), "m"))
    rows.append(("nl_vs_cw_scaling", "circular", "loglog_slope", slope, "-"))
    dk = r.docking
    cross = dk.y_crossings()
    rows.append(("docking", "circular", "dock_time", r.options.dock_time_s, "s"))
    cm_at_dock = np.array([np.interp(r.options.dock_time_s, dk.t, dk.cm_nl[:, j]) for j in range(3)])
    rows.append(("docking", "circular", "nl_cm_distance_at_dock_time", float(np.linalg.norm(cm_at_dock)), "m"))
    rows.append(("docking", "cm", "y_zero_crossing_time", float(cross[0]), "s"))
    for i, ci in enumerate(cross[1:], start=1):
        rows.append(("docking", f"P{i}", "y_zero_crossing_time", float(ci), "s"))
    fs = r.features
    rows += [
        ("coupled_vs_simplified", "all_points", "max_feature_difference", float(fs.difference.max()), "m"),
        ("coupled_vs_simplified", "all_points", "integration_error_estimate", float(fs.integration_error.max()), "m"),
        ("coupled_vs_simplified", "all_points", "max_feature_difference_as_printed",
         float(fs.printed_difference.max()), "m"),
        ("coupled_vs_simplified", "all_points", "max_feature_offset_from_cm",
         float(np.linalg.norm(fs.simplified - fs.cm[:, None, :], axis=-1).max()), "m"),
        ("coupled_vs_simplified", "all_points", "nfev_simplified", float(fs.nfev_simplified), "-"),
        ("coupled_vs_simplified", "all_points", "nfev_coupled", float(fs.nfev_coupled), "-"),
        ("coupled_vs_simplified", "all_points", "horizon", float(fs.t[-1]), "s"),
    ]
    for i in range(fs.difference.shape[1]):
        d_i = float(fs.difference[:, i].max())
        rows.append(("coupled_vs_simplified", f"P{i + 1}", "max_feature_difference", d_i, "m"))
    for _, row in r.timing.iterrows():
        case = f"N={int(row['N'])}"
        for col in r.timing.columns:
            if col == "N":
                continue
            unit = "s" if col.endswith("_s") else "%" if col.endswith("_pct") else "-"
            rows.append(("timing", case, col, float(row[col]), unit))
    return pd.DataFrame(rows, columns=["study", "case", "quantity", "value", "unit"])


# ----------------------------------------------------------------------------- outputs


def _md(df: pd.DataFrame, floatfmt: str = "{:.4g}") -> str:
    cols = list(df.columns)
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for _, row in df.iterrows():
        cells = [floatfmt.format(v) if isinstance(v, float) else str(v) for v in row]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def markdown_report(r: DynamicsResult, summary: pd.DataFrame, command: str | None) -> str:
    """``dynamics.md``: the summary tables (a), (b), (c) in Markdown."""
    parts = [f"# Dynamical-model studies: {r.scenario}", ""]
    if command:
        parts += [f"Command: `{command}`", ""]
    nl = summary[summary.study.str.startswith("nl_vs_cw") | (summary.study == "docking")]
    parts += ["## (a) Nonlinear vs Clohessy-Wiltshire (figs 2.5-2.7)", "",
              f"Horizon {r.horizon:.1f} s; CW at n = sqrt(mu/a^3); scenario duration {r.scenario_duration:g} s.", "",
              _md(nl), ""]
    fb = summary[summary.study == "coupled_vs_simplified"]
    parts += ["## (b) Simplified vs Segal-Gurfil coupled feature model (figs 2.3-2.4)", "", _md(fb), ""]
    tm = r.timing.copy()
    parts += ["## (c) Cost vs number of feature points (figs 2.8-2.10)", "",
              "Shortest of the interleaved timed runs: wall time `t_*`, process CPU time `cpu_*`; "
              "v% = (t_coupled - t_simplified)/t_coupled from the CPU times.", "",
              _md(tm), ""]
    return "\n".join(parts)


def make_figures(r: DynamicsResult, out: Path) -> list[Path]:
    """Draw and save the figures of the three studies; returns the written files."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files: list[Path] = []
    comp = ("x", "y", "z")

    def done(fig, stem: str) -> None:
        files.extend(save_figure(fig, out, stem))
        plt.close(fig)

    # (a) figs 2.5-2.6: components and difference, circular and eccentric
    for c in r.cw_cases:
        fig, axes = plt.subplots(4, 1, figsize=(8, 9), sharex=True, layout="constrained")
        for j in range(3):
            axes[j].plot(c.t, c.nonlinear[:, j], label="nonlinear")
            axes[j].plot(c.t, c.cw[:, j], "--", label="CW")
            axes[j].set_ylabel(f"{comp[j]} [m]")
        axes[0].legend()
        axes[3].semilogy(c.t[1:], np.maximum(c.difference[1:], 1e-300), color="k")
        axes[3].set_ylabel("|NL - CW| [m]")
        axes[3].set_xlabel("t [s]")
        fig.suptitle(f"{r.scenario}: c.m. relative position, nonlinear vs CW, {c.name} orbit (e = {c.orbit.e:g})")
        done(fig, f"cw_{c.name}")
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2), layout="constrained")
    for c in r.cw_cases:
        a1.semilogy(c.t[1:], c.difference[1:], label=f"{c.name} (e = {c.orbit.e:g})")
    a1.set_xlabel("t [s]")
    a1.set_ylabel("|rho_NL - rho_CW| [m]")
    a1.legend()
    f, d, slope = r.scaling
    a2.loglog(f, d, "o-", label=f"circular, slope {slope:.3f}")
    a2.loglog(f, d[0] * (f / f[0]) ** 2, ":", color="gray", label="slope 2")
    a2.set_xlabel("scale of initial relative state")
    a2.set_ylabel("max |rho_NL - rho_CW| [m]")
    a2.legend()
    fig.suptitle(f"{r.scenario}: CW linearization error")
    done(fig, "cw_difference")
    # (a) fig 2.7: docking
    dk = r.docking
    cross = dk.y_crossings()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2), layout="constrained")
    a1.plot(dk.t, dk.cm_cw[:, 1], "k", lw=2, label=f"c.m. (CW), y=0 at {cross[0]:.1f} s")
    a1.plot(dk.t, dk.cm_nl[:, 1], "k:", label="c.m. (nonlinear)")
    for i in range(dk.features_cw.shape[1]):
        a1.plot(dk.t, dk.features_cw[:, i, 1], label=f"P{i + 1}, y=0 at {cross[i + 1]:.1f} s")
        a2.plot(dk.t, np.linalg.norm(dk.features_cw[:, i], axis=-1), label=f"P{i + 1}")
    a2.plot(dk.t, np.linalg.norm(dk.cm_cw, axis=-1), "k", lw=2, label="c.m. (CW)")
    a1.axhline(0.0, color="gray", lw=0.5)
    a1.set_xlabel("t [s]")
    a1.set_ylabel("y (along-track) [m]")
    a1.legend(fontsize=7)
    a2.set_xlabel("t [s]")
    a2.set_ylabel("distance to leader c.m. [m]")
    a2.legend(fontsize=7)
    fig.suptitle(f"{r.scenario}: docking at {r.options.dock_time_s:g} s (CW intercept, circular orbit)")
    done(fig, "cw_docking")
    # (b) figs 2.3-2.4
    fs = r.features
    N = fs.simplified.shape[1]
    step = max(1, fs.t.size // 40)
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True, layout="constrained")
    for j in range(3):
        axes[j].plot(fs.t, fs.cm[:, j], "k", lw=1.5, label="c.m.")
        for i in range(N):
            line, = axes[j].plot(fs.t, fs.simplified[:, i, j], lw=1, label=f"P{i + 1} simplified")
            axes[j].plot(fs.t[::step], fs.coupled[::step, i, j], "o", ms=3, mfc="none", color=line.get_color(),
                         label=f"P{i + 1} coupled")
        axes[j].set_ylabel(f"{comp[j]} [m]")
    axes[0].legend(fontsize=6, ncol=2)
    axes[2].set_xlabel("t [s]")
    fig.suptitle(f"{r.scenario}: feature-point positions in L (lines: simplified, circles: coupled)")
    done(fig, "features")
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True, layout="constrained")
    for j in range(3):
        for i in range(N):
            axes[j].plot(fs.t, fs.simplified[:, i, j] - fs.cm[:, j], label=f"P{i + 1}")
        axes[j].set_ylabel(f"delta {comp[j]} [m]")
    axes[0].legend(fontsize=7)
    axes[2].set_xlabel("t [s]")
    fig.suptitle(f"{r.scenario}: feature-point deviation from the c.m., rho_i - rho_0 = D P_i")
    done(fig, "feature_deviation")
    fig, ax = plt.subplots(figsize=(8, 4.5), layout="constrained")
    for i in range(N):
        line, = ax.semilogy(fs.t[1:], np.maximum(fs.difference[1:, i], 1e-16), lw=1, label=f"P{i + 1} coupled")
        ax.semilogy(fs.t[1:], fs.printed_difference[1:, i], "--", lw=1, color=line.get_color(),
                    label=f"P{i + 1} as printed")
    ax.semilogy(fs.t[1:], np.maximum(fs.integration_error[1:].max(axis=1), 1e-16), "k:",
                label=f"integration error (rtol {r.options.rtol:g} vs {r.options.rtol_reference:g})")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("|rho_i - rho_i,simplified| [m]")
    ax.legend(fontsize=7, ncol=2)
    fig.suptitle(f"{r.scenario}: coupled (Segal-Gurfil) vs simplified feature model")
    done(fig, "coupled_vs_simplified")
    # (c) figs 2.8-2.10
    tm = r.timing
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2), layout="constrained")
    for m, mk in (("rk4", "o"), ("dop853", "s")):
        ls, = a1.loglog(tm.N, tm[f"cpu_{m}_simplified_s"], mk + "-", label=f"simplified (13+3N), {m}")
        lc, = a1.loglog(tm.N, tm[f"cpu_{m}_coupled_s"], mk + "--", label=f"coupled (13+9N), {m}")
        a1.loglog(tm.N, tm[f"t_{m}_simplified_s"], "x", color=ls.get_color(), alpha=0.5)
        a1.loglog(tm.N, tm[f"t_{m}_coupled_s"], "x", color=lc.get_color(), alpha=0.5)
        a2.semilogx(tm.N, tm[f"v_{m}_pct"], mk + "-", label=m)
    a1.set_xlabel("feature points N")
    a1.set_ylabel("CPU time [s] (x: wall time)")
    a1.legend(fontsize=7)
    a2.axhline(0.0, color="gray", lw=0.5)
    a2.set_xlabel("feature points N")
    a2.set_ylabel("v% = (t_coupled - t_simplified) / t_coupled [%]")
    a2.legend()
    fig.suptitle(f"{r.scenario}: propagation cost vs number of feature points")
    done(fig, "timing")
    return files


def write_outputs(r: DynamicsResult, out: Path, command: list[str] | None = None) -> list[Path]:
    """Figures, ``dynamics.csv``/``.md``, ``timing.csv`` and ``manifest.json`` into ``out`` (must exist)."""
    out = Path(out)
    files = make_figures(r, out)
    summary = summary_frame(r)
    for name, df in (("dynamics.csv", summary), ("timing.csv", r.timing)):
        store.atomic_write_text(out / name, df.to_csv(index=False, float_format="%.10g"))
        files.append(out / name)
    cmd = " ".join(command) if command else None
    store.atomic_write_text(out / "dynamics.md", markdown_report(r, summary, cmd) + "\n")
    files.append(out / "dynamics.md")
    manifest = {**store.base_manifest(command), "kind": "dynamics", "scenario": r.scenario,
                "options": asdict(r.options), "horizon_s": r.horizon, "files": sorted(p.name for p in files)}
    store.write_json(out / "manifest.json", manifest)
    files.append(out / "manifest.json")
    return files


def summary_lines(r: DynamicsResult) -> list[str]:
    """The printed summary: one line per headline number."""
    circ, ecc = r.cw_cases
    fs = r.features
    cross = r.docking.y_crossings()
    in_dur = circ.t <= r.scenario_duration + 1e-9
    timing = ", ".join(
        f"{int(row.N)}: {row.cpu_rk4_simplified_s * 1e3:.1f}/{row.cpu_rk4_coupled_s * 1e3:.1f} ms "
        f"[{row.v_rk4_pct:.0f}%]"
        for row in r.timing.itertuples()
    )
    lines = [
        f"{r.scenario}: horizon {r.horizon:.0f} s",
        f"(a) max |NL - CW|: circular {circ.difference.max():.4g} m, eccentric (e={ecc.orbit.e:g}) "
        f"{ecc.difference.max():.4g} m; within {r.scenario_duration:g} s: {circ.difference[in_dur].max():.3g} m / "
        f"{ecc.difference[in_dur].max():.3g} m; circular log-log slope {r.scaling[2]:.3f}",
        f"    docking at {r.options.dock_time_s:g} s: y = 0 at c.m. {cross[0]:.1f} s, points "
        + ", ".join(f"{c:.1f}" for c in cross[1:]) + " s",
        f"(b) max |coupled - simplified| {fs.difference.max():.3g} m "
        f"(integration error {fs.integration_error.max():.3g} m; "
        f"thesis signs as printed: {fs.printed_difference.max():.3g} m)",
        f"(c) N: CPU time simplified / coupled (RK4, {r.options.timing_duration_s or r.scenario_duration:g} s) "
        f"[v%]: {timing}",
    ]
    return lines


def run_dynamics(
    scn: Scenario, out: Path, options: StudyOptions = StudyOptions(), overwrite: bool = False,
    command: list[str] | None = None,
) -> DynamicsResult:
    """Run the studies and write everything into ``out`` (refuses a non-empty ``out`` unless ``overwrite``).

    The directory is checked before any computation, and created only when the results are ready.
    """
    out = Path(out)
    store.check_replaceable(out, overwrite)
    r = run_studies(scn, options)
    staged = store.build_dir(out, overwrite, lambda d: (d, write_outputs(r, d, command)))
    r.files = [out / p.relative_to(staged[0]) for p in staged[1]]
    return r
