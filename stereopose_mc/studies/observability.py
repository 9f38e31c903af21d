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

from ..config import Scenario
from ..config.resolve import Setup, setup_of
from ..core import camera, jacobians
from ..core import observability as ob
from ..core import quaternion as qt
from ..core import state as st
from ..core.kalman import transition_matrix
from ..core.layout import OMEGA, QUAT, QUAT_SIZE, RHO, RHO_DOT, VEC, k_offset, n_points, point
from ..core.orbit import leader_kinematics
from ..sim.measurements import channel_sigmas
from ..sim.truth import Truth, simulate_truth
from .jsonfmt import fmt_vec, vec

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


# --------------------------------------------------------------------------- Hermann-Krener (thesis ch. 4)


def euler_observability(omega_degps, inertia, order: int = 1, rtol: float | None = None) -> dict[str, Any]:
    """The thesis's ch. 4 Hermann-Krener test at ``[omega, inertia]`` as a JSON-ready dict.

    ``null_space`` is a list of unit vectors (one per unobservable direction) in the state
    ``[w_x, w_y, w_z, I_x, I_y, I_z]`` (rad/s, kg m^2); ``singular_values`` are those of ``O``
    in SI units; ``scaled_singular_values`` those that decide the rank (unit-free).
    """
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
        "omega_radps": vec(omega),
        "inertia_kgm2": vec(inertia),
        "order": order,
        "rows": int(3 * (order + 1)),
        "rank": res.rank,
        "null_space": [vec(v) for v in null],
        "singular_values": vec(res.singular_values),
        "scaled_singular_values": vec(res.scaled_singular_values),
        "rtol": res.rtol,
        "null_space_is_inertia_scale": bool(scale_only),
    }


def rank_report_lines(r: dict[str, Any]) -> list[str]:
    """Text form of a rank-test dict (shared by every observability analysis)."""
    out: list[str] = []
    n = len(r["state"])
    out.append(
        f"rank {r['rank']} of {n} (O is {r['rows']} x {n}; "
        f"relative threshold {r['rtol']:g} on the scaled singular values)"
    )
    out.append("singular values of O (SI entries): " + " ".join(f"{s:.4e}" for s in r["singular_values"]))
    out.append("scaled singular values (s/s_max): " + " ".join(f"{s:.4e}" for s in r["scaled_singular_values"]))
    if not r["null_space"]:
        out.append("null space: empty (locally weakly observable)")
        return out
    names = ", ".join(r["state"])
    out.append(f"null space ({len(r['null_space'])} unobservable direction(s), unit vectors over {names}):")
    for v in r["null_space"]:
        out.append("  " + fmt_vec(v, "9.6f"))
    return out


# --------------------------------------------------------------------------- text form of filter_state_observability


def _e(x: float) -> str:
    return f"{x:.3e}"


def filter_state_lines(r: dict[str, Any]) -> list[str]:
    """Text form of the ``--filter-state`` dict."""
    out: list[str] = []
    names = r["state_names"]
    out.append(
        f"Observability Gramian of the filter state along the true trajectory of {r['scenario']} "
        f"({r['scenario_file']}): {r['duration_s']:g} s, dt {r['dt_s']:g} s, {r['measurement_rows']} measurement rows, "
        f"pseudo-measurement {'on' if r['pseudo_measurement'] else 'off'}, "
        f"omega0 = {fmt_vec(r['omega0_degps'], '.4g')} deg/s"
    )
    out.append("W = sum_k Phi(t_k,t_0)^T H_k^T R^-1 H_k Phi(t_k,t_0), R = the truth's noise; "
               "scaled W~ = S W S with S = sqrt(diag P0) (unit-free)")  # fmt: skip
    out.append(f"largest eigenvalue of W~: {_e(r['lambda_max'])}; values below are relative to it "
               f"(round-off floor n eps = {r['roundoff_floor'] / r['lambda_max']:.1e})")  # fmt: skip
    qn = r["q_norm"]
    out.append(
        f"quaternion norm direction: unobservable by construction (|H_k e_q| / |H_k| <= {qn['max_rel_H_eq']:.1e}); "
        f"Rayleigh quotient {qn['relative_rayleigh']:.1e} (discretization of Phi); projected out"
    )
    gauge = " ".join(f"{v:.1e}" for v in r["gauge_relative_eigenvalues"])
    fixed = "projected out" if "gauge_x" in r["projected_out"] else "kept (--keep-gauge)"
    out.append(f"body-frame gauge (rotate q and all P_i together; images unchanged): W~ on it {gauge}; {fixed}")
    com = " ".join(f"{v:.1e}" for v in r["com_shift_relative_eigenvalues"])
    out.append(f"centre-of-mass shift (all P_i by c, rho by -D c; images unchanged at t_0): W~ on it {com}")
    rel = r["relative_eigenvalues"]
    out.append(f"eigenvalues of W~ ({len(rel)}, ascending, relative): " + " ".join(f"{v:.2e}" for v in rel))
    cond = r["condition_number"]
    out.append(
        f"relative condition lambda_min/lambda_max = {r['relative_condition']:.2e}"
        + ("" if cond is not None else " (smallest eigenvalue at round-off)")
    )
    out.append(f"weakest {len(r['weak_directions'])} directions (unit vectors in scaled coordinates):")
    for d in r["weak_directions"]:
        comps = ", ".join(f"{k} {v:+.2f}" for k, v in d["components"].items())
        out.append(
            f"  {d['relative']:.2e}  {comps}   [k {d['k_share']:.2f}, com shift {d['com_shift_share']:.2f}, "
            f"gauge {d['gauge_share']:.2f}]"
        )
    out.append("CRLB sqrt(diag((W + P0^-1)^-1)) (SI: m, m/s, rad/s, -, m, -):")
    sig = r["crlb_sigma"]
    n = len(names)
    blocks = [names[RHO:RHO_DOT], names[RHO_DOT:OMEGA], names[OMEGA:QUAT], names[QUAT : QUAT + QUAT_SIZE]]
    blocks += [names[point(i) : point(i) + VEC] for i in range(n_points(n))] + [names[k_offset(n) :]]
    for b in blocks:
        out.append("  " + "  ".join(f"{k} {sig[k]:.3e}" for k in b))
    rms = r["crlb_rms"]
    out.append(
        f"  RMS error bounds: rho {rms['rho_m']:.3g} m, rho_dot {rms['rho_dot_mps']:.3g} m/s, "
        f"omega {rms['omega_degps']:.3g} deg/s, theta {rms['theta_deg']:.3g} deg, "
        f"k1 {rms['k1']:.3g}, k2 {rms['k2']:.3g}"
    )
    km = r["k_sigma_measurements_only"]
    out.append(f"  k from the measurements alone (no prior on k): k1 {km['k1']:.3g}, k2 {km['k2']:.3g}")
    return out
