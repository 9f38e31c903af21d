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

from ..config.resolve import Setup
from ..core import dynamics, state as st
from ..core import quaternion as qt
from ..core import perturbed
from ..core.orbit import Orbit, elements_to_rv, leader_kinematics, mean_to_true, true_to_mean

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Truth:
    t: Array  # (K+1,)
    nu: Array  # (K+1,) leader true anomaly
    nu_dot: Array
    nu_ddot: Array
    x: Array  # (K+1, n) true state
    alpha: Array  # (K+1, 3) true relative angular acceleration omega_dot, in L
    # perturbed truth (truth_model): the Keplerian orbit the filter uses over [t_k, t_k+1], i.e. the
    # leader's osculating orbit at t_k (the chaser knows its own orbit); None: setup.orbit throughout
    filter_orbits: tuple | None = None
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

    from scipy.integrate import solve_ivp  # here, not at import: ~0.2 s, and a cached truth needs none

    sol = solve_ivp(rhs, (t[0], t[-1]), x0, method="DOP853", t_eval=t, rtol=rtol, atol=rtol * scale * 1e-2)
    if not sol.success:  # pragma: no cover - DOP853 on a smooth problem
        raise RuntimeError(f"truth integration failed: {sol.message}")
    return sol.y.T


def simulate_truth(setup: Setup) -> Truth:
    if setup.perturbations is not None:
        return simulate_perturbed_truth(setup)
    t = setup.times
    x = integrate(setup.x0, t, setup, setup.truth_rtol)
    x[:, st.QUAT] = qt.normalize(x[:, st.QUAT])
    lk = leader_kinematics(setup.orbit, t)
    # contiguous (not a view of f's output): the truth cache stores and gives back this memory layout
    alpha = np.ascontiguousarray(dynamics.f(x, lk.r, lk.nu_dot, lk.nu_ddot, setup.orbit.mu)[:, st.OMEGA])
    return Truth(t=t, nu=lk.nu, nu_dot=lk.nu_dot, nu_ddot=lk.nu_ddot, x=x, alpha=alpha)


# ---------------------------------------------------------------------------------------------
# Perturbed truth (scenario key ``truth_model``): both spacecraft and the target's attitude are
# propagated in the inertial frame (core/perturbed.py) and converted to the leader's LVLH frame
# with the frame's full angular velocity w_F = [r a_h / h, 0, h / r^2]. Batch-first: ``x0 (B, n)``.


def inertial_state(orbit, x0: Array, p) -> Array:
    """Inertial ``y (B, 19)`` of relative states ``x0 (B, n)`` with the leader at the orbit's epoch.

    The leader starts on the orbit's elements (its osculating orbit at t = 0); the
    target's inertial velocity is ``v_L + R_IL (rho_dot + w_F x rho)`` and its inertial
    rate ``w_T = D^T (omega + w_F)``, with the frame's full rate ``w_F`` (``a_h`` of the
    perturbations ``p``), the inverse of ``relative_state``.
    """
    x0 = np.atleast_2d(x0)
    B = x0.shape[0]
    rl, vl = elements_to_rv(orbit)
    R = perturbed.lvlh_axes(rl, vl)
    wF = perturbed.lvlh_rate(rl, vl, perturbed.perturbing_accel(rl, vl, p.ballistic_leader, p))
    rho, rho_dot = x0[:, st.RHO], x0[:, st.RHO_DOT]
    D = qt.dcm(qt.normalize(x0[:, st.QUAT]))
    y = np.empty((B, perturbed.N_STATE))
    y[:, perturbed.R_L], y[:, perturbed.V_L] = rl, vl
    y[:, perturbed.R_T] = rl + rho @ R.T
    y[:, perturbed.V_T] = vl + (rho_dot + qt.cross(wF, rho)) @ R.T
    y[:, perturbed.Q_IT] = qt_from_dcm(R @ D)
    y[:, perturbed.W_T] = np.einsum("bji,bj->bi", D, x0[:, st.OMEGA] + wF)
    return y


def relative_state(Y: Array, x0: Array, p) -> tuple[Array, Array]:
    """LVLH states ``(B, K+1, n)`` and frame rates ``w_F (B, K+1, 3)`` from inertial ``Y (B, K+1, 19)``.

    ``rho = R_IL^T (r_T - r_L)``, ``rho_dot = R_IL^T (v_T - v_L) - w_F x rho``,
    ``D = R_IL^T R(q_IT)``, ``omega = D w_T - w_F``; feature points and k from ``x0 (B, n)``;
    the quaternion's sign is kept continuous, starting from ``x0``'s.
    """
    rl, vl = Y[..., perturbed.R_L], Y[..., perturbed.V_L]
    R = perturbed.lvlh_axes(rl, vl)
    wF = perturbed.lvlh_rate(rl, vl, perturbed.perturbing_accel(rl, vl, p.ballistic_leader, p))
    rho = np.einsum("...ji,...j->...i", R, Y[..., perturbed.R_T] - rl)
    rho_dot = np.einsum("...ji,...j->...i", R, Y[..., perturbed.V_T] - vl) - qt.cross(wF, rho)
    D = np.swapaxes(R, -1, -2) @ qt.dcm(Y[..., perturbed.Q_IT])
    omega = np.einsum("...ij,...j->...i", D, Y[..., perturbed.W_T]) - wF
    q = qt_from_dcm(D)
    ref = np.atleast_2d(x0)[:, None, st.QUAT]
    for k in range(q.shape[-2]):  # sign continuity along time
        s = np.sign(np.sum(q[..., k, :] * ref[..., 0, :], axis=-1))
        q[..., k, :] *= np.where(s == 0, 1.0, s)[..., None]
        ref = q[..., k : k + 1, :]
    x = np.broadcast_to(np.atleast_2d(x0)[:, None, :], rho.shape[:-1] + (x0.shape[-1],)).copy()
    x[..., st.RHO], x[..., st.RHO_DOT], x[..., st.OMEGA], x[..., st.QUAT] = rho, rho_dot, omega, q
    return x, wF


def qt_from_dcm(D: Array) -> Array:
    """Scalar-first quaternion ``(..., 4)`` of rotation matrices ``(..., 3, 3)`` (``D = dcm(q)``)."""
    from scipy.spatial.transform import Rotation

    flat = D.reshape(-1, 3, 3)
    return Rotation.from_matrix(flat).as_quat(scalar_first=True).reshape(D.shape[:-2] + (4,))


def _target_moments(x0: Array) -> Array:
    N = st.n_points(x0.shape[-1])
    k = x0[..., st.k_slice(N)]
    return np.stack([np.exp(k[..., 0]), np.ones_like(k[..., 0]), np.exp(-k[..., 1])], axis=-1)


def perturbed_relative(setup: Setup, x0: Array, t: Array) -> tuple[Array, Array, Array]:
    """Batch-first perturbed truth: ``x (B, K+1, n)``, ``alpha (B, K+1, 3)``, inertial ``Y (B, K+1, 19)``.

    ``alpha = D w_T' + omega x w_F - w_F'``, the relative angular acceleration in ``L``
    (``w_T'`` from Euler's equation with the torque, ``w_F'`` by a central difference of
    the frame rate on the integrator's continuous solution, step 1e-2 s).
    """
    p = setup.perturbations
    x0 = np.atleast_2d(x0)
    J = _target_moments(x0)
    Y, sol = perturbed.propagate(inertial_state(setup.orbit, x0, p), t, J, p, setup.truth_rtol, dense=True)
    x, wF = relative_state(Y, x0, p)
    d = perturbed.rhs(Y, J[:, None, :], p)
    D = qt.dcm(x[..., st.QUAT])
    h = 1e-2
    tp = np.clip(t + h, t[0], t[-1])
    tm = np.clip(t - h, t[0], t[-1])

    def rate(tt):
        Yt = np.moveaxis(np.stack([sol(v) for v in tt]), 0, 1)
        rl, vl = Yt[..., perturbed.R_L], Yt[..., perturbed.V_L]
        return perturbed.lvlh_rate(rl, vl, perturbed.perturbing_accel(rl, vl, p.ballistic_leader, p))

    wF_dot = (rate(tp) - rate(tm)) / (tp - tm)[:, None]
    alpha = np.einsum("...ij,...j->...i", D, d[..., perturbed.W_T]) + qt.cross(x[..., st.OMEGA], wF) - wF_dot
    return x, alpha, Y


def filter_orbit_at(Y_leader: Array, t: float, mu: float) -> Orbit:
    """The Keplerian orbit through the leader's inertial state ``(6,)`` at time ``t`` (its osculating orbit).

    Its epoch stays t = 0 (``nu0`` is moved back along the osculating orbit) so that
    ``leader_kinematics(orbit, t)`` gives the osculating ``r, nu_dot, nu_ddot`` at ``t``.
    """
    el = perturbed.osculating_elements(Y_leader[:3], Y_leader[3:6], mu)
    a, e = float(el["a"]), float(el["e"])
    M0 = true_to_mean(float(el["nu"]), e) - np.sqrt(mu / a**3) * t
    return Orbit(a=a, e=e, i=float(el["i"]), raan=float(el["raan"]), argp=float(el["argp"]),
                 nu0=float(mean_to_true(M0, e)), mu=mu)  # fmt: skip


def simulate_perturbed_truth(setup: Setup) -> Truth:
    """The scenario's truth with ``truth_model`` perturbations (one trajectory; see ``perturbed_relative``)."""
    t = setup.times
    x, alpha, Y = perturbed_relative(setup, setup.x0[None], t)
    x, alpha, Y = x[0], alpha[0], Y[0]
    orbits = tuple(filter_orbit_at(Y[k, :6], float(t[k]), setup.orbit.mu) for k in range(t.size))
    # the leader's osculating anomaly and frame rate, for outputs (the filters use ``filter_orbits``)
    lk = [leader_kinematics(o, tk) for o, tk in zip(orbits, t)]
    nu = np.array([float(v.nu) for v in lk])
    nu_dot = np.array([float(v.nu_dot) for v in lk])
    nu_ddot = np.array([float(v.nu_ddot) for v in lk])
    return Truth(t=t, nu=nu, nu_dot=nu_dot, nu_ddot=nu_ddot, x=x, alpha=alpha, filter_orbits=orbits)
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
