"""Local observability of the full filter state along a scenario's true trajectory.

``spmc observability --filter-state SCENARIO``: the discrete observability Gramian

    W = sum_{k=1..K} Phi(t_k, t_0)^T H_k^T R^-1 H_k Phi(t_k, t_0)

of the filter's linearized model at the TRUE states (numerics in
``core/observability.py``), analysed in scaled, unit-free coordinates. Choices:

- ``Phi(t_{k+1}, t_k) = expm(F(x(t_k)) dt)`` with the analytic ``F`` at the true state at
  the start of the step (as the filter does at its estimate), chained step by step;
- measurement rows at ``t_1 .. t_K`` (the filter's first update is at ``t = dt``): the
  eight (or nine, with disparity) channels of every feature visible at ``t_k`` and, when
  the scenario enables it, the three pseudo-measurement rows with ``alpha`` the true
  angular acceleration;
- ``R``: the truth's noise, ``channel_sigmas(setup)`` per image channel and
  ``sigma_alpha`` per pseudo row (Euler's residual rotates ``alpha``'s isotropic noise by
  ``D^T``, which keeps it isotropic). This is the information the measurements really
  carry, not what a filter with a looser ``R`` extracts; a differentiated
  angular-acceleration source (``alpha_method`` other than ``truth_plus_noise``) is not
  modelled: ``sigma_alpha`` stands for its noise;
- scale ``S = sqrt(diag P0)``: ``z = S^-1 delta x`` is in units of the initial standard
  deviations, and ``P0^-1`` becomes the identity in the CRLB's information matrix.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .config import Scenario
from .config.resolve import Setup, setup_of
from .core import camera, jacobians
from .core import observability as ob
from .core import quaternion as qt
from .core import state as st
from .core.filters import transition_matrix
from .core.orbit import leader_kinematics
from .sim.measurements import channel_sigmas
from .sim.truth import Truth, simulate_truth

Array = NDArray[np.float64]
DEG = np.pi / 180.0
DEFAULT_WEAK = 5


@dataclass(frozen=True)
class FilterGramian:
    """The Gramian of one scenario and what it was built from."""

    setup: Setup
    truth: Truth
    W: Array  # (n, n), SI state units
    rows_per_step: Array  # (K+1,) measurement rows used at each time (0 at t_0)


def with_duration(setup: Setup, duration_s: float | None) -> Setup:
    """``setup`` with ``steps = round(duration_s / dt)`` (unchanged when ``None``)."""
    if duration_s is None:
        return setup
    steps = int(round(duration_s / setup.dt))
    if steps < 1:
        raise ValueError(f"the horizon {duration_s} s is shorter than one step (dt = {setup.dt} s)")
    return dataclasses.replace(setup, steps=steps)


def measurement_model(setup: Setup, truth: Truth) -> tuple[Array, Array]:
    """``H (K+1, m, n)`` and the weights ``1/sigma^2`` ``(K+1, m)`` at the true states.

    Rows: ``N`` features x ``C`` channels (weight 0 when the feature is not visible), then
    3 pseudo-measurement rows if enabled. Every weight at ``t_0`` is 0 (no update there).
    """
    sig = channel_sigmas(setup)
    if np.any(sig <= 0):
        raise ValueError(
            "the Gramian needs nonzero truth noise: measurements.image_sigma / flow_sigma / disparity_sigma "
            f"are {sig.tolist()} (a noise-free channel carries infinite information)"
        )
    x = truth.x
    K1, n = x.shape
    Hf = jacobians.H_features(x, setup.baseline, setup.disparity, setup.focal)  # (K+1, N, C, n)
    N, C = Hf.shape[1], Hf.shape[2]
    vis = camera.visible(x)  # (K+1, N)
    wf = vis[:, :, None] / sig[None, None, :] ** 2
    H = [Hf.reshape(K1, N * C, n)]
    w = [np.broadcast_to(wf, (K1, N, C)).reshape(K1, N * C)]
    if setup.pseudo:
        H.append(jacobians.H_pseudo(x, truth.alpha, truth.nu_dot, truth.nu_ddot))
        w.append(np.full((K1, 3), 1.0 / setup.sigma_alpha**2))
    H_all = np.concatenate(H, axis=1)
    w_all = np.concatenate(w, axis=1)
    w_all[0] = 0.0
    return H_all, w_all


def step_transitions(setup: Setup, truth: Truth) -> Array:
    """``expm(F(x(t_k)) dt)`` ``(K, n, n)`` for ``k = 0 .. K-1`` (analytic ``F`` at the truth)."""
    lk = leader_kinematics(setup.orbit, truth.t[:-1])
    Fk = jacobians.F(truth.x[:-1], lk.r, lk.nu_dot, lk.nu_ddot, setup.orbit.mu)
    return transition_matrix(Fk, setup.dt, method="expm")


def filter_gramian(setup: Setup) -> FilterGramian:
    """The observability Gramian of the filter state along the scenario's true trajectory."""
    truth = simulate_truth(setup)
    H, w = measurement_model(setup, truth)
    W = ob.observability_gramian(step_transitions(setup, truth), H, w)
    return FilterGramian(setup=setup, truth=truth, W=W, rows_per_step=np.count_nonzero(w, axis=1))


def _block_summary(C: Array, x0: Array, n_points: int) -> dict[str, float]:
    """RMS sizes of the error vectors from a covariance ``C``: ``sqrt(trace)`` of a block
    (rho m, rho_dot m/s, omega deg/s), the attitude angle (deg) from the rotation vector
    ``2 Q(q)^T delta q`` (unit ``q``), and k1, k2."""
    Q = qt.omega_matrix(qt.normalize(x0[st.QUAT]))
    Cq = C[st.QUAT, st.QUAT]
    ks = st.k_slice(n_points)
    return {
        "rho_m": float(np.sqrt(np.trace(C[st.RHO, st.RHO]))),
        "rho_dot_mps": float(np.sqrt(np.trace(C[st.RHO_DOT, st.RHO_DOT]))),
        "omega_degps": float(np.sqrt(np.trace(C[st.OMEGA, st.OMEGA])) / DEG),
        "theta_deg": float(np.sqrt(np.trace(4.0 * Q.T @ Cq @ Q)) / DEG),
        "k1": float(np.sqrt(C[ks, ks][0, 0])),
        "k2": float(np.sqrt(C[ks, ks][1, 1])),
    }


def analyse(g: FilterGramian, weak: int = DEFAULT_WEAK, fix_gauge: bool = True) -> dict[str, Any]:
    """The scaled eigen-analysis and the CRLB of one Gramian, as a JSON-ready dict.

    The quaternion-norm direction is always projected out (unobservable by construction);
    the three body-frame gauge directions too unless ``fix_gauge`` is False. The Gramian
    restricted to the gauge subspace and to the centre-of-mass shifts (not projected out)
    is reported either way, as eigenvalues relative to the largest of ``W~``.
    """
    setup, x0 = g.setup, g.truth.x[0]
    n = x0.size
    N = st.n_points(n)
    ks = st.k_slice(N)
    names = ob.filter_state_names(N)
    scale = np.sqrt(setup.P0_diag)
    u_q = ob.scaled_basis(ob.quaternion_norm_direction(x0), scale)
    B_g = ob.scaled_basis(ob.gauge_directions(x0), scale)
    B_c = ob.scaled_basis(ob.com_shift_directions(x0), scale)
    fixed = ob.scaled_basis(np.hstack([u_q, B_g]), np.ones(n)) if fix_gauge else u_q
    e = ob.gramian_eigen(g.W, scale, fixed)
    lam, V, lmax = e.eigenvalues, e.eigenvectors, e.lambda_max

    def restricted(B: Array) -> list[float]:
        return [float(v / lmax) for v in np.linalg.eigvalsh(B.T @ e.scaled_gramian @ B)]

    weak_dirs = []
    for i in range(min(weak, lam.size)):
        v = V[:, i]
        weak_dirs.append(
            {
                "eigenvalue": float(lam[i]),
                "relative": float(lam[i] / lmax),
                "components": dict(ob.describe_direction(v, names)),
                "k_share": float(np.sum(v[ks] ** 2)),
                "com_shift_share": ob.subspace_share(v, B_c),
                "gauge_share": ob.subspace_share(v, B_g),
            }
        )

    C = ob.crlb_covariance(g.W, setup.P0_diag)
    no_k_prior = np.zeros(n, bool)
    no_k_prior[ks] = True
    Ck = ob.crlb_covariance(g.W, setup.P0_diag, no_prior=no_k_prior)[ks, ks]
    return {
        "analysis": "filter_state_gramian",
        "duration_s": float(setup.steps * setup.dt),
        "dt_s": float(setup.dt),
        "steps": int(setup.steps),
        "pseudo_measurement": bool(setup.pseudo),
        "omega0_degps": [float(v) for v in x0[st.OMEGA] / DEG],
        "measurement_rows": int(g.rows_per_step.sum()),
        "noise": {
            "image_sigma": float(setup.sigma_image),
            "flow_sigma": float(setup.sigma_flow),
            "disparity_sigma": float(setup.sigma_disparity) if setup.disparity else None,
            "alpha_sigma_radps2": float(setup.sigma_alpha) if setup.pseudo else None,
        },
        "state_names": list(names),
        "scaling": {k: float(v) for k, v in zip(names, scale)},
        "projected_out": ["q_norm"] + (["gauge_x", "gauge_y", "gauge_z"] if fix_gauge else []),
        "lambda_max": lmax,
        "roundoff_floor": e.floor,
        "eigenvalues": [float(v) for v in lam],
        "relative_eigenvalues": [float(v / lmax) for v in lam],
        "relative_condition": float(max(lam[0], 0.0) / lmax),
        "condition_number": float(lmax / lam[0]) if lam[0] > e.floor else None,
        "weak_directions": weak_dirs,
        "q_norm": {
            "relative_rayleigh": float(e.fixed_rayleigh[0] / lmax),
            "max_rel_H_eq": _max_rel_H_eq(g),
        },
        "gauge_relative_eigenvalues": restricted(B_g),
        "com_shift_relative_eigenvalues": restricted(B_c),
        "crlb_sigma": {k: float(v) for k, v in zip(names, np.sqrt(np.diag(C)))},
        "crlb_rms": _block_summary(C, x0, N),
        "k_sigma_measurements_only": {"k1": float(np.sqrt(Ck[0, 0])), "k2": float(np.sqrt(Ck[1, 1]))},
    }


def _max_rel_H_eq(g: FilterGramian) -> float:
    """``max_k |H_k e_q(t_k)| / max |H_k|``: ``h`` is neutral to ``q``'s scale at every step."""
    H, w = measurement_model(g.setup, g.truth)
    e = ob.quaternion_norm_direction(g.truth.x)  # (K+1, n)
    He = np.einsum("kmn,kn->km", H, e)
    return float(np.max(np.abs(He)) / np.max(np.abs(H)))


def filter_state_observability(
    s: Scenario, duration_s: float | None = None, weak: int = DEFAULT_WEAK, fix_gauge: bool = True
) -> dict[str, Any]:
    """Build the Gramian of scenario ``s`` (over ``duration_s`` if given) and analyse it."""
    g = filter_gramian(with_duration(setup_of(s), duration_s))
    return {"scenario": s.name, **analyse(g, weak=weak, fix_gauge=fix_gauge)}
