"""UKF and MEKF kernels against independent references (issue 10, item 6).

- a linear-Gaussian system: the unscented kernels (any scaling) and the MEKF's error-state
  update equal the textbook Kalman filter;
- a nonlinear toy model: the UKF kernels equal FilterPy's ``UnscentedKalmanFilter`` step
  by step (FilterPy redraws nothing between predict and update; we redraw the sigma
  points from ``(x-, P-)``, so the reference is given the same points);
- the relative-navigation problem near linearity: EKF, MEKF and UKF agree.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from stereopose_mc.config import load_scenario_text
from stereopose_mc.config.resolve import filter_setup_of, setup_of
from stereopose_mc.core import kalman as kf
from stereopose_mc.core import unscented as ut
from stereopose_mc.mc.trial import Bounds, run_chunk
from stereopose_mc.sim import measurements as meas
from stereopose_mc.sim.truth import simulate_truth

from scenarios import scenario_dict

RNG = np.random.default_rng(11)


def textbook(x, P, F, Q, H, R, y):
    """One predict + update of the linear Kalman filter, explicit algebra (reference only)."""
    x, P = F @ x, F @ P @ F.T + Q
    S = H @ P @ H.T + np.diag(R)
    K = P @ H.T @ np.linalg.inv(S)
    return x + K @ (y - H @ x), (np.eye(len(x)) - K @ H) @ P


@pytest.mark.parametrize("alpha,beta,kappa", [(0.5, 2.0, 0.0), (1.0, 0.0, 1.0), (1e-2, 2.0, 0.0)])
def test_ukf_equals_the_linear_kalman_filter(alpha, beta, kappa):
    B, n, m = 3, 4, 2
    A = RNG.standard_normal((B, n, n))
    P = A @ np.swapaxes(A, -1, -2) + np.eye(n)
    x = RNG.standard_normal((B, n))
    F = np.eye(n) + 0.1 * RNG.standard_normal((n, n))
    Q = 0.05 * np.eye(n)
    H = RNG.standard_normal((m, n))
    R = np.array([0.3, 0.7])
    y = RNG.standard_normal((B, m))
    xp, Pp = ut.predict(x, P, lambda s, i: s @ F.T, Q, alpha, beta, kappa)
    xu, Pu, nu, nis = ut.update(xp, Pp, y, lambda s, i: s @ H.T, R, alpha, beta, kappa)
    for b in range(B):
        xr, Pr = textbook(x[b], P[b], F, Q, H, R, y[b])
        np.testing.assert_allclose(xu[b], xr, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(Pu[b], Pr, rtol=1e-7, atol=1e-9)
    # the MEKF's update is the EKF kernel on the error state: on a linear model, the same numbers
    u = kf.ekf_update(xp, Pp, y, lambda s, rows, jac=True: (s @ H.T, np.broadcast_to(H, (s.shape[0], m, n)).copy()),
                      R, np.arange(B))  # fmt: skip
    np.testing.assert_allclose(u.x, xu, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(u.P, Pu, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(u.nis, nis, rtol=1e-7)


def fx(s, dt=0.1):
    """Pendulum-like toy: angle, rate, a damping parameter."""
    th, w, c = s[..., 0], s[..., 1], s[..., 2]
    return np.stack([th + dt * w, w - dt * (9.81 * np.sin(th) + c * w), c], axis=-1)


def hx(s):
    """Nonlinear measurement: sine and cosine of the angle times a range, and the rate squared."""
    return np.stack([2.0 * np.sin(s[..., 0]), 2.0 * np.cos(s[..., 0]) + s[..., 1] ** 2], axis=-1)


def test_ukf_matches_filterpy_on_a_nonlinear_toy():
    alpha, beta, kappa = 0.3, 2.0, 0.5
    Q = np.diag([1e-4, 1e-3, 1e-5])
    R = np.array([0.05, 0.02])
    x0, P0 = np.array([0.8, 0.0, 0.3]), np.diag([0.2, 0.5, 0.05])
    ref = UnscentedKalmanFilter(dim_x=3, dim_z=2, dt=0.1, fx=lambda s, dt: fx(s, dt), hx=hx,
                                points=MerweScaledSigmaPoints(3, alpha, beta, kappa))  # fmt: skip
    ref.x, ref.P, ref.Q, ref.R = x0.copy(), P0.copy(), Q, np.diag(R)
    x, P = x0[None].copy(), P0[None].copy()
    truth = np.array([1.0, -0.2, 0.3])
    for k in range(30):
        truth = fx(truth)
        y = hx(truth) + RNG.standard_normal(2) * np.sqrt(R)
        ref.predict()
        ref.sigmas_f = ref.points_fn.sigma_points(ref.x, ref.P)  # redraw, as our update does
        ref.update(y)
        x, P = ut.predict(x, P, lambda s, i: fx(s), Q, alpha, beta, kappa)
        x, P, nu, nis = ut.update(x, P, y[None], lambda s, i: hx(s), R, alpha, beta, kappa)
        np.testing.assert_allclose(x[0], ref.x, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(P[0], ref.P, rtol=1e-8, atol=1e-12)
    assert np.abs(x[0, 0] - truth[0]) < 0.2  # it also tracks


def test_ekf_mekf_ukf_agree_near_linearity():
    """Small initial errors (nearly linear): every filter and error state gives nearly the same errors, all consistent.

    The full-state EKF, the EKF and the MEKF in the aligned and attitude error states are the
    same filter to first order (the charts differ at second order): the same errors to 2 %;
    the UKFs (second-order in the mean) the same medians to 20 %.
    """
    scn = load_scenario_text(yaml.safe_dump(scenario_dict(
        "caseB", time={"dt_s": 1.0, "duration_s": 12.0, "error_window_start_s": 2.0},
        initial_covariance={"rho_m2": 1e-2, "rho_dot_m2ps2": 1e-6, "omega_deg2ps2": 1e-4, "q": 1e-7,
                            "feature_points_m2": 1e-3, "k": 1e-3},
        filters=[{"type": "ekf", "error_state": "full"}, {"type": "ekf", "name": "ekf_aligned"},
                 {"type": "mekf", "iterated": False, "error_state": "attitude"},
                 {"type": "mekf", "name": "mekf_aligned", "iterated": False, "error_state": "aligned"},
                 {"type": "ukf", "error_state": "attitude"}, {"type": "ukf", "name": "ukf_aligned"}])))  # fmt: skip
    setup = setup_of(scn)
    truth = simulate_truth(setup)
    exact = meas.noise_free(setup, truth)
    fs = [filter_setup_of(f, setup) for f in scn.filters]
    ekf, ekf_al, mekf, mekf_al, ukf, ukf_al = run_chunk(scn.seed, np.arange(8), setup, truth, exact, fs, Bounds()).runs
    # the MEKF (attitude chart) is the EKF to first order: the same errors to 2 %
    np.testing.assert_allclose(mekf.errors[:, 1:], ekf.errors[:, 1:], rtol=0.02, atol=1e-6)
    # the EKF in an error state is the MEKF with one update per step: the same arithmetic
    np.testing.assert_array_equal(ekf_al.errors, mekf_al.errors)
    # the aligned chart differs from the additive one at second order (the centroid is D(q) P_bar): medians to 10 %,
    # the UKFs (second-order in the mean) to 20 %
    w = np.s_[:, 2:]

    def med(r):
        return np.median(np.mean(r.errors[w], 1), 0)

    np.testing.assert_allclose(med(ekf_al), med(ekf), rtol=0.1)
    for r in (ukf, ukf_al):
        np.testing.assert_allclose(med(r), med(ekf), rtol=0.2, err_msg=r.label)
    for r in (ekf_al, mekf, mekf_al, ukf, ukf_al):
        assert (r.diverged_step < 0).all()
        # error-state covariance (n - 1 = 29), every NEES reported in the attitude chart: 29 dof
        assert 10 < np.mean(r.nees[:, 1:]) < 60, r.label
        assert r.x_final.shape == ekf.x_final.shape and r.P_final.shape[-1] == ekf.P_final.shape[-1] - 1


def test_weighted_outer_is_the_weighted_sum_of_outer_products():
    """``weighted_outer(W, a, b) = sum_k W_k a_k b_k^T`` per trial, negative weights included (``Wc_0 < 0`` for a
    small ``alpha``): against the sum written out, and a hand value."""
    W = np.array([-3.0, 0.5, 0.25])
    a = RNG.standard_normal((4, 3, 5))
    b = RNG.standard_normal((4, 3, 2))
    ref = np.zeros((4, 5, 2))
    for t in range(4):
        for k in range(3):
            ref[t] += W[k] * np.outer(a[t, k], b[t, k])
    np.testing.assert_allclose(ut.weighted_outer(W, a, b), ref, rtol=1e-14, atol=1e-14)
    one = ut.weighted_outer(np.array([2.0, -1.0]), np.array([[[1.0, 2.0], [3.0, 0.0]]]), np.array([[[1.0], [1.0]]]))
    np.testing.assert_array_equal(one, [[[2.0 - 3.0], [4.0]]])
