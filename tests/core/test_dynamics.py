"""Relative dynamics: rotating-frame kinematics, Euler's equations, Clohessy-Wiltshire limit, RK4 order."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs
from reference import inertial
from reference.truth_setups import setup_from

from stereopose_mc.core import dynamics, state as st
from stereopose_mc.core.orbit import MU_EARTH
from stereopose_mc.sim.truth import integrate, simulate_truth

finite = dict(allow_nan=False, allow_infinity=False)
vec3 = hs.lists(hs.floats(-1.0, 1.0, **finite), min_size=3, max_size=3).map(np.array)
quat = hs.lists(hs.floats(-1.0, 1.0, **finite), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.2)
kpair = hs.tuples(hs.floats(-1.0, 1.0), hs.floats(-1.0, 1.0))


def _leader_from_inertial(e: float, nu: float):
    """``(r_L, nu', nu'', R_IL, r, v)`` from the reference's inertial leader (no package orbit code)."""
    el = inertial.Elements(a=7.5e6, e=e, i=0.7, raan=1.1, argp=-0.4, nu0=nu)
    r, v = inertial.kepler_rv(el, nu)
    rn = np.linalg.norm(r)
    nu_dot = inertial.lvlh_rate(r, v)
    r_dot = np.dot(r, v) / rn
    nu_ddot = -2.0 * r_dot * nu_dot / rn  # d/dt (|h| / r^2) with |h| constant
    return rn, nu_dot, nu_ddot, inertial.lvlh_axes(r, v), r, v


@settings(max_examples=60, deadline=None)
@given(e=hs.floats(0.0, 0.5), nu=hs.floats(-np.pi, np.pi), rho=vec3, rho_dot=vec3, size=hs.floats(1.0, 3.0))
def test_translation_equals_inertial_difference_in_rotating_frame(e, nu, rho, rho_dot, size):
    """``rho'' = R^T (a_T - a_L) - 2 w x rho' - w x (w x rho) - w' x rho`` with two-body a_T, a_L."""
    r_L, nu_dot, nu_ddot, R, r, _ = _leader_from_inertial(e, nu)
    rho = rho * 10**size  # 10 m .. 1 km
    rho_dot = rho_dot * 10 ** (size - 2)
    w, w_dot = np.array([0.0, 0.0, nu_dot]), np.array([0.0, 0.0, nu_ddot])
    rT = r + R @ rho
    a_rel = -MU_EARTH * rT / np.linalg.norm(rT) ** 3 + MU_EARTH * r / np.linalg.norm(r) ** 3
    expected = R.T @ a_rel - 2 * np.cross(w, rho_dot) - np.cross(w, np.cross(w, rho)) - np.cross(w_dot, rho)
    got = dynamics.translational_acceleration(rho, rho_dot, r_L, nu_dot, nu_ddot)
    np.testing.assert_allclose(got, expected, rtol=1e-8, atol=1e-13)


@settings(max_examples=60, deadline=None)
@given(e=hs.floats(0.0, 0.5), nu=hs.floats(-np.pi, np.pi), omega=vec3, q=quat, k=kpair)
def test_rotation_equals_euler_in_body_frame(e, nu, omega, q, k):
    """``w' = w x (D w_T) + D w_T' - w_L'`` (derivative of ``w = D w_T - w_L`` with ``D' = [w x] D``)."""
    _, nu_dot, nu_ddot, *_ = _leader_from_inertial(e, nu)
    omega = 0.05 * omega
    k = np.asarray(k)
    moments = np.array([np.exp(k[0]), 1.0, np.exp(-k[1])])
    D = inertial.quat_to_matrix(q)
    wL = np.array([0.0, 0.0, nu_dot])
    w_T = D.T @ (omega + wL)
    w_T_dot = np.linalg.solve(np.diag(moments), -np.cross(w_T, moments * w_T))
    expected = np.cross(omega, D @ w_T) + D @ w_T_dot - np.array([0.0, 0.0, nu_ddot])
    w_dot, q_dot = dynamics.rotational_rates(omega, np.asarray(q), k, nu_dot, nu_ddot)
    np.testing.assert_allclose(w_dot, expected, rtol=1e-9, atol=1e-16)
    # q' = 1/2 q (x) [0, D^T w]: the relative rate (not w_T) drives q
    qn = np.asarray(q) / np.linalg.norm(q)
    _, q_dot_n = dynamics.rotational_rates(omega, qn, k, nu_dot, nu_ddot)
    expected_q = 0.5 * inertial.quat_rate_matrix(D.T @ omega) @ qn
    np.testing.assert_allclose(q_dot_n, expected_q, rtol=1e-10, atol=1e-16)


def test_f_keeps_batch_axes():
    """``f`` on ``(n,)``, ``(B, n)`` and ``(B, C, n)`` gives the same rows and the input's shape."""
    rng = np.random.default_rng(3)
    n = st.size(4)
    X = rng.normal(size=(2, 3, n))
    X[..., st.RHO] *= 50.0
    X[..., st.OMEGA] *= 0.02
    args = (7.0e6, 1.1e-3, 2e-8)
    full = dynamics.f(X, *args)
    assert full.shape == X.shape
    assert dynamics.f(X[0], *args).shape == (3, n)
    for b in range(2):
        for c in range(3):
            np.testing.assert_array_equal(dynamics.f(X[b, c], *args), full[b, c])
    # points and k are constant
    assert np.all(full[..., st.POINTS0 :] == 0.0)


def test_rk4_is_fourth_order():
    """``propagate`` against a tight DOP853 solution: halving the step divides the error by ~16."""
    setup = setup_from(
        leader={"orbit": {"a_km": 8000.0, "e": 0.2, "true_anomaly_deg": 10.0}},
        truth_initial_state={"rho_m": [10.0, 60.0, 10.0], "rho_dot_mps": [0.05, -0.1, 0.02],
                             "omega_degps": [3.0, -4.0, 2.0], "q": [0.9, 0.1, 0.3, -0.2]},
    )  # fmt: skip
    dt = 20.0
    exact = integrate(setup.x0, np.array([0.0, dt]), setup, 1e-13)[-1]
    errs = [np.abs(dynamics.propagate(setup.x0, 0.0, dt, setup.orbit, m) - exact).max() for m in (4, 8, 16)]
    ratios = np.array(errs[:-1]) / np.array(errs[1:])
    assert np.all((ratios > 14.0) & (ratios < 18.0)), (errs, ratios)


# ------------------------------------------------------------------ Clohessy-Wiltshire


def cw(rho0: np.ndarray, v0: np.ndarray, n: float, t: np.ndarray) -> np.ndarray:
    """Closed-form Clohessy-Wiltshire solution (x radial, y along-track, z normal), ``(K, 3)``.

    x = 4x0 - 3x0 cos nt + (vx0/n) sin nt + (2vy0/n)(1 - cos nt)
    y = y0 + 6x0 (sin nt - nt) - (2vx0/n)(1 - cos nt) + (vy0/n)(4 sin nt - 3nt)
    z = z0 cos nt + (vz0/n) sin nt
    """
    x0, y0, z0 = rho0
    vx, vy, vz = v0
    c, s, nt = np.cos(n * t), np.sin(n * t), n * t
    x = 4 * x0 - 3 * x0 * c + vx / n * s + 2 * vy / n * (1 - c)
    y = y0 + 6 * x0 * (s - nt) - 2 * vx / n * (1 - c) + vy / n * (4 * s - 3 * nt)
    z = z0 * c + vz / n * s
    return np.stack([x, y, z], axis=-1)


A_CW = 6878.0e3


def _cw_case(scale: float):
    """Nonlinear truth vs CW on a circular orbit over ~one period; returns (max |diff|, max |rho|, t, n)."""
    n = np.sqrt(MU_EARTH / A_CW**3)
    rho0 = scale * np.array([1.0, 2.0, 0.5])
    v0 = scale * n * np.array([0.5, -2.0, 1.0])  # vy0 = -2 n x0: no secular drift in CW
    setup = setup_from(
        time={"dt_s": 60.0, "duration_s": 5700.0, "error_window_start_s": 10.0},
        leader={"orbit": {"a_km": A_CW / 1e3, "e": 0.0, "i_deg": 51.6}},
        truth_initial_state={"rho_m": rho0.tolist(), "rho_dot_mps": v0.tolist(),
                             "omega_degps": [0.5, 0.2, -0.3], "q": [1.0, 0.0, 0.0, 0.0]},
    )  # fmt: skip
    assert setup.orbit.e == 0.0 and abs(setup.times[-1] * n / (2 * np.pi) - 1.0) < 0.01
    truth = simulate_truth(setup)
    rho_nl = truth.x[:, st.RHO]
    rho_cw = cw(rho0, v0, n, truth.t)
    diff = np.linalg.norm(rho_nl - rho_cw, axis=-1)
    return diff, max(np.linalg.norm(rho_nl, axis=-1).max(), np.linalg.norm(rho_cw, axis=-1).max()), truth.t, n


@pytest.fixture(scope="module")
def cw_runs():
    return {s: _cw_case(s) for s in (25.0, 50.0)}


def test_cw_matches_nonlinear_to_second_order(cw_runs):
    """|rho_NL - rho_CW|(t) <= 3 n^2 rho_max^2 / r (1.5 t^2 + 10 t / n), with margin 1.2.

    The second-order gravity term is (3 mu / 2 r^4) [2 x rho + (|rho|^2 - 5 x^2) e_x], of norm at most
    3 n^2 |rho|^2 / r; the CW response (velocity Green's function, norm <= 3 tau + 10 / n) to a forcing of
    norm <= a over [0, t] is at most a (1.5 t^2 + 10 t / n).
    """
    for diff, rho_max, t, n in cw_runs.values():
        bound = 1.2 * 3 * n**2 * rho_max**2 / A_CW * (1.5 * t**2 + 10 * t / n)
        assert np.all(diff <= bound + 1e-9)
        assert diff.max() > 1e-3 * bound.max()  # and the nonlinearity is really there (not a linear model)
        assert diff.max() < 1e-3 * rho_max


def test_cw_difference_scales_quadratically(cw_runs):
    """Doubling the separation multiplies the CW-vs-nonlinear difference by 4 (second order)."""
    d1, d2 = cw_runs[25.0][0], cw_runs[50.0][0]
    ratio = d2.max() / d1.max()
    assert abs(ratio - 4.0) < 0.05, ratio
    # pointwise too, where the difference is not tiny
    big = d1 > 0.1 * d1.max()
    np.testing.assert_allclose(d2[big] / d1[big], 4.0, rtol=0.02)
