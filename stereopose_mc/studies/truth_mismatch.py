"""How far the perturbed truth (``truth_model``) departs from the filters' model.

Two measures per effect (J2, drag, gravity-gradient torque, each alone, then all that
the scenario enables together):

- **drift**: the perturbed truth against the Keplerian, torque-free truth from the
  same initial state, over the scenario (what the filters' model would predict open
  loop): position ``|rho_p - rho_k|``, attitude angle between ``q_p`` and ``q_k``,
  angular velocity ``|omega_p - omega_k|``;
- **one-step model error**: from the true state at ``t_k``, the filters' prediction
  (RK4 of the Keplerian relative model fed the leader's osculating orbit at ``t_k``,
  20 substeps) against the truth at ``t_k+1``; its largest value over the scenario is
  the unmodelled motion the filters' process noise ``Q`` has to cover per step.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from ..config.resolve import Setup
from ..core import dynamics, state as st
from ..core import quaternion as qt
from ..rundir import store
from ..sim.truth import Truth, simulate_truth
from .figure_files import save_figure

Array = NDArray[np.float64]
RAD2DEG = 180.0 / np.pi
SUBSTEPS = 20


@dataclass
class Mismatch:
    effect: str
    t: Array
    drift_rho: Array  # (K+1,) m
    drift_theta: Array  # (K+1,) rad
    drift_omega: Array  # (K+1,) rad/s
    step_rho: Array  # (K,) m
    step_rho_dot: Array  # (K,) m/s
    step_theta: Array  # (K,) rad
    step_omega: Array  # (K,) rad/s


def effects(setup: Setup) -> dict[str, object]:
    """The perturbation sets to compare: each enabled effect alone, then all of them."""
    p = setup.perturbations
    if p is None:
        return {}
    off = dataclasses.replace(p, j2=False, drag=False, gravity_gradient=False)
    out = {}
    for name, flag in (("j2", "j2"), ("drag", "drag"), ("gravity_gradient", "gravity_gradient")):
        if getattr(p, flag):
            out[name] = dataclasses.replace(off, **{flag: True})
    if len(out) != 1:
        out["all"] = p
    return out


def one_step_errors(setup: Setup, truth: Truth) -> tuple[Array, Array, Array, Array]:
    """Per step ``k``: the filters' model from the true ``x(t_k)`` against ``x(t_k+1)``."""
    x = truth.x
    K = x.shape[0] - 1
    pred = np.empty_like(x[1:])
    for k in range(K):
        orbit = truth.filter_orbits[k] if truth.filter_orbits is not None else setup.orbit
        pred[k] = dynamics.propagate(x[k : k + 1], float(truth.t[k]), setup.dt, orbit, SUBSTEPS)[0]
    d = pred - x[1:]
    return (np.linalg.norm(d[:, st.RHO], axis=-1), np.linalg.norm(d[:, st.RHO_DOT], axis=-1),
            qt.error_angle(x[1:, st.QUAT], qt.normalize(pred[:, st.QUAT])), np.linalg.norm(d[:, st.OMEGA], axis=-1))  # fmt: skip


def mismatch_study(setup: Setup) -> list[Mismatch]:
    """Drift and one-step model error of each effect (empty without ``truth_model``)."""
    kep = simulate_truth(dataclasses.replace(setup, perturbations=None))
    out = []
    for name, p in effects(setup).items():
        tr = simulate_truth(dataclasses.replace(setup, perturbations=p))
        s = one_step_errors(setup, tr)
        out.append(Mismatch(
            name, tr.t, np.linalg.norm(tr.x[:, st.RHO] - kep.x[:, st.RHO], axis=-1),
            qt.error_angle(kep.x[:, st.QUAT], tr.x[:, st.QUAT]),
            np.linalg.norm(tr.x[:, st.OMEGA] - kep.x[:, st.OMEGA], axis=-1), *s,
        ))  # fmt: skip
    return out


def mismatch_frame(ms: list[Mismatch]) -> pd.DataFrame:
    """One row per effect: final and largest drift, largest one-step model error."""
    rows = []
    for m in ms:
        rows.append({
            "effect": m.effect,
            "drift_rho_final_m": m.drift_rho[-1], "drift_rho_max_m": m.drift_rho.max(),
            "drift_theta_max_deg": m.drift_theta.max() * RAD2DEG, "drift_omega_max_degps": m.drift_omega.max() * RAD2DEG,
            "step_rho_max_m": m.step_rho.max(), "step_rho_dot_max_mps": m.step_rho_dot.max(),
            "step_theta_max_deg": m.step_theta.max() * RAD2DEG, "step_omega_max_degps": m.step_omega.max() * RAD2DEG,
        })  # fmt: skip
    return pd.DataFrame(rows)


def markdown(df: pd.DataFrame, duration: float) -> str:
    head = ("| effect | drift rho, final [m] | drift rho, max [m] | drift theta, max [deg] | drift omega, max [deg/s] "
            "| 1-step rho [m] | 1-step rho_dot [m/s] | 1-step theta [deg] | 1-step omega [deg/s] |")
    lines = [f"## Truth-model mismatch over {duration:g} s (drift: perturbed vs Keplerian torque-free truth; "
             "1-step: the filters' model over one step from the true state, largest over the scenario)", "",
             head, "|" + "---|" * 9]  # fmt: skip
    for r in df.to_dict("records"):
        vals = [r[c] for c in df.columns[1:]]
        lines.append(f"| {r['effect']} | " + " | ".join(f"{v:.3g}" for v in vals) + " |")
    return "\n".join(lines)


def figure(ms: list[Mismatch], out: Path) -> list[Path]:
    """``truth_mismatch.png/.svg``: position and attitude drift vs time per effect."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8), constrained_layout=True)
    for m in ms:
        ax[0].plot(m.t, m.drift_rho, label=m.effect)
        ax[1].plot(m.t, m.drift_theta * RAD2DEG, label=m.effect)
    ax[0].set(xlabel="t [s]", ylabel="|rho_perturbed - rho_Keplerian| [m]", title="position drift")
    ax[1].set(xlabel="t [s]", ylabel="attitude difference [deg]", title="attitude drift")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend()
    paths = list(save_figure(fig, out, "truth_mismatch"))
    plt.close(fig)
    return paths


def write_mismatch(setup: Setup, out: Path) -> tuple[pd.DataFrame, list[Path]]:
    """Run the study and write ``truth_mismatch.csv``, ``.md`` and the figure into ``out``."""
    ms = mismatch_study(setup)
    df = mismatch_frame(ms)
    out = Path(out)
    store.atomic_write_text(out / "truth_mismatch.csv", df.to_csv(index=False, float_format="%.10g"))
    store.atomic_write_text(out / "truth_mismatch.md", markdown(df, float(setup.times[-1])) + "\n")
    return df, [out / "truth_mismatch.csv", out / "truth_mismatch.md", *figure(ms, out)]


def summary_lines(df: pd.DataFrame) -> list[str]:
    return [f"(d) truth_model {r['effect']}: drift rho {r['drift_rho_max_m']:.3g} m, theta "
            f"{r['drift_theta_max_deg']:.3g} deg; 1-step model error rho {r['step_rho_max_m']:.3g} m, "
            f"omega {r['step_omega_max_degps']:.3g} deg/s" for r in df.to_dict("records")]  # fmt: skip
