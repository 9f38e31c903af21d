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
from ..core.orbit import leader_kinematics

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Truth:
    t: Array  # (K+1,)
    nu: Array  # (K+1,) leader true anomaly
    nu_dot: Array
    nu_ddot: Array
    x: Array  # (K+1, n) true state
    alpha: Array  # (K+1, 3) true relative angular acceleration omega_dot, in L

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
