"""The true trajectory of a scenario: one per scenario, shared by all its trials.

The state ``x = [rho, rho_dot, omega, q, P, k]`` is integrated with scipy's DOP853 at
relative tolerance ``time.truth_rtol`` (default 1e-12) and per-component absolute
tolerances scaled to each block, then sampled at ``t_k = k dt``. The quaternion is not
renormalized during the integration (the kinematics preserve its norm to the
integration tolerance); it is normalized at the output.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.integrate import solve_ivp

from ..config.resolve import Setup
from ..core import dynamics, state as st
from ..core import quaternion as qt
from ..core.orbit import Orbit, leader_kinematics

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Truth:
    t: Array  # (K+1,)
    nu: Array  # (K+1,) leader true anomaly
    nu_dot: Array
    nu_ddot: Array
    x: Array  # (K+1, n) true state
    alpha: Array  # (K+1, 3) true relative angular acceleration omega_dot, in L
    # (simulate_truth_batch: a leading trial axis on nu, nu_dot, nu_ddot, x and alpha; t stays (K+1,))

    @property
    def n_points(self) -> int:
        return st.n_points(self.x.shape[-1])


def integrate(x0: Array, t: Array, setup: Setup, rtol: float) -> Array:
    """High-accuracy integration of ``f`` from ``t[0]`` through the times ``t``."""
    orbit = setup.orbit
    n = x0.size
    N = st.n_points(n)
    scale = np.ones(n)
    scale[st.RHO] = max(1.0, float(np.linalg.norm(x0[st.RHO])))
    scale[st.RHO_DOT] = max(1e-3, float(np.linalg.norm(x0[st.RHO_DOT])))
    scale[st.OMEGA] = max(1e-3, float(np.linalg.norm(x0[st.OMEGA])))
    scale[st.points_slice(N)] = 1.0

    def rhs(tt, y):
        return dynamics.f_at(y, tt, orbit)

    sol = solve_ivp(rhs, (t[0], t[-1]), x0, method="DOP853", t_eval=t, rtol=rtol, atol=rtol * scale * 1e-2)
    if not sol.success:  # pragma: no cover - DOP853 on a smooth problem
        raise RuntimeError(f"truth integration failed: {sol.message}")
    return sol.y.T


def simulate_truth(setup: Setup) -> Truth:
    t = setup.times
    x = integrate(setup.x0, t, setup, setup.truth_rtol)
    x[:, st.QUAT] = qt.normalize(x[:, st.QUAT])
    lk = leader_kinematics(setup.orbit, t)
    alpha = dynamics.f(x, lk.r, lk.nu_dot, lk.nu_ddot, setup.orbit.mu)[:, st.OMEGA]
    return Truth(t=t, nu=lk.nu, nu_dot=lk.nu_dot, nu_ddot=lk.nu_ddot, x=x, alpha=alpha)


# ------------------------------------------------------------- per-trial truth (issue 11)


def _leader_state(orbits: list[Orbit]) -> Array:
    """``[r_L, r_dot_L, nu, h_L]`` at t = 0 per orbit, ``(B, 4)`` (``h_L = sqrt(mu p)``, constant)."""
    out = np.empty((len(orbits), 4))
    for i, o in enumerate(orbits):
        c = 1.0 + o.e * np.cos(o.nu0)
        out[i] = [o.p / c, np.sqrt(o.mu / o.p) * o.e * np.sin(o.nu0), o.nu0, np.sqrt(o.mu * o.p)]
    return out


def _leader_rates(lead: Array, mu: float) -> tuple[Array, Array, Array, Array]:
    """``r_L, nu_dot, nu_ddot`` and ``d/dt [r_L, r_dot_L, nu, h_L]`` from ``lead (..., 4)``."""
    r, r_dot, h = lead[..., 0], lead[..., 1], lead[..., 3]
    nu_dot = h / (r * r)
    nu_ddot = -2.0 * r_dot * nu_dot / r
    d = np.stack([r_dot, r * nu_dot * nu_dot - mu / (r * r), nu_dot, np.zeros_like(r)], axis=-1)
    return r, nu_dot, nu_ddot, d


def simulate_truth_batch(x0: Array, orbits: list[Orbit], t: Array, rtol: float) -> Truth:
    """The truths of ``B`` trials together, trial axis first: ``x (B, K+1, n)``, ``nu (B, K+1)``...

    Each trial has its own initial state ``x0[b]`` and leader orbit ``orbits[b]`` (same
    ``mu``). The leader's Keplerian motion is integrated with the relative state (``r_L``,
    ``r_dot_L``, ``nu`` and the constant ``h_L``; the two-body radial equation
    ``r'' = h^2 / r^3 - mu / r^2``, ``nu' = h / r^2``) by ``core.integrate.dop853_batch`` at
    ``rtol``, with the absolute tolerances of ``integrate`` per trial, so each trial's truth
    is the same bits in any batch. Accuracy: docs/truth-accuracy.md.
    """
    x0 = np.atleast_2d(np.asarray(x0, dtype=float))
    B, n = x0.shape
    N = st.n_points(n)
    mu = orbits[0].mu
    lead0 = _leader_state(orbits)
    y0 = np.concatenate([x0, lead0], axis=-1)
    scale = np.ones((B, n + 4))
    scale[:, st.RHO] = np.maximum(1.0, np.linalg.norm(x0[:, st.RHO], axis=-1))[:, None]
    scale[:, st.RHO_DOT] = np.maximum(1e-3, np.linalg.norm(x0[:, st.RHO_DOT], axis=-1))[:, None]
    scale[:, st.OMEGA] = np.maximum(1e-3, np.linalg.norm(x0[:, st.OMEGA], axis=-1))[:, None]
    scale[:, st.points_slice(N)] = 1.0
    scale[:, n] = lead0[:, 0]
    scale[:, n + 1] = np.maximum(1.0, np.abs(lead0[:, 1]))
    scale[:, n + 3] = lead0[:, 3]

    def rhs(y):
        r, nu_dot, nu_ddot, dlead = _leader_rates(y[:, n:], mu)
        return np.concatenate([dynamics.f(y[:, :n], r, nu_dot, nu_ddot, mu), dlead], axis=-1)

    from ..core.integrate import dop853_batch

    y = dop853_batch(rhs, y0, np.asarray(t, dtype=float), rtol, rtol * scale * 1e-2)
    x = y[..., :n].copy()
    x[..., st.QUAT] = qt.normalize(x[..., st.QUAT])
    r, nu_dot, nu_ddot, _ = _leader_rates(y[..., n:], mu)
    alpha = dynamics.f(x, r, nu_dot, nu_ddot, mu)[..., st.OMEGA]
    return Truth(t=np.asarray(t, dtype=float), nu=y[..., n + 2], nu_dot=nu_dot, nu_ddot=nu_ddot, x=x, alpha=alpha)
