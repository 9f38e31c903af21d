"""The filter kernels on a linear-Gaussian problem against a textbook Kalman filter."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stereopose_mc.core import kalman as kf


def textbook_kf(x, P, y, H, R):
    """Kalman (1960) in its covariance form, one trial, with explicit algebra."""
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)  # the reference may invert: it is not the code under test
    x_new = x + K @ (y - H @ x)
    P_new = (np.eye(len(x)) - K @ H) @ P
    return x_new, P_new, S


def random_problem(rng, B, n, m):
    A = rng.standard_normal((B, n, n))
    P = A @ np.swapaxes(A, -1, -2) + n * np.eye(n)
    H = rng.standard_normal((m, n))
    R = rng.uniform(0.1, 2.0, m)
    x = rng.standard_normal((B, n))
    y = rng.standard_normal((B, m)) * 3
    return x, P, H, R, y


def linear_measure(H):
    def measure(x, rows, jac=True):
        hx = x @ H.T
        return hx, (np.broadcast_to(H, (x.shape[0],) + H.shape).copy() if jac else None)

    return measure


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 8), m=st.integers(1, 6))
def test_ekf_equals_textbook_kalman_filter(seed, n, m):
    rng = np.random.default_rng(seed)
    B = 4
    x, P, H, R, y = random_problem(rng, B, n, m)
    u = kf.ekf_update(x, P, y, linear_measure(H), R, np.arange(B))
    for b in range(B):
        xr, Pr, Sr = textbook_kf(x[b], P[b], y[b], H, np.diag(R))
        np.testing.assert_allclose(u.x[b], xr, rtol=1e-10, atol=1e-10)
        # Joseph form equals (I - KH)P for the optimal gain
        np.testing.assert_allclose(u.P[b], Pr, rtol=1e-9, atol=1e-10)
        nu = y[b] - H @ x[b]
        np.testing.assert_allclose(u.nis[b], nu @ np.linalg.solve(Sr, nu), rtol=1e-10)
        # to round-off of the terms (y and H x nearly cancel in some draws: a relative test of the difference fails)
        scale = np.abs(y[b]) + np.abs(H) @ np.abs(x[b])
        np.testing.assert_array_less(np.abs(u.nu[b] - (y[b] - H @ x[b])), 1e-13 * scale + 1e-300)


@pytest.mark.parametrize("step_control", ["none", "line_search", "levenberg_marquardt"])
def test_iekf_with_linear_h_equals_the_ekf(step_control):
    rng = np.random.default_rng(7)
    B, n, m = 6, 5, 4
    x, P, H, R, y = random_problem(rng, B, n, m)
    ekf = kf.ekf_update(x, P, y, linear_measure(H), R, np.arange(B))
    it1 = kf.iekf_update(x, P, y, linear_measure(H), R, np.arange(B), tol=1e-8, max_iter=1, step_control="none")
    np.testing.assert_allclose(it1.x, ekf.x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(it1.P, ekf.P, rtol=1e-12, atol=1e-12)
    it = kf.iekf_update(x, P, y, linear_measure(H), R, np.arange(B), tol=1e-8, max_iter=10, step_control=step_control)
    np.testing.assert_allclose(it.x, ekf.x, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(it.P, ekf.P, rtol=1e-9, atol=1e-12)
    assert it.converged.all()
    if step_control != "levenberg_marquardt":
        # the first Gauss-Newton step lands on the solution; the second step is zero and stops it
        assert (it.iterations == 2).all()


def test_joseph_form_keeps_symmetry_and_positivity_for_a_suboptimal_gain():
    rng = np.random.default_rng(3)
    x, P, H, R, y = random_problem(rng, 3, 4, 3)
    Hb = np.broadcast_to(H, (3, 3, 4))
    S = kf.innovation_covariance(P, Hb, R)
    K = 1.7 * np.swapaxes(np.linalg.solve(S, Hb @ P), -1, -2)  # deliberately not optimal
    Pj = kf.joseph(P, K, Hb, R)
    np.testing.assert_array_equal(Pj, np.swapaxes(Pj, -1, -2))
    assert (np.linalg.eigvalsh(Pj) > 0).all()
    for b in range(3):
        IKH = np.eye(4) - K[b] @ H
        ref = IKH @ P[b] @ IKH.T + K[b] @ np.diag(R) @ K[b].T
        np.testing.assert_allclose(Pj[b], ref, rtol=1e-12)


def test_transition_matrix_taylor_matches_expm():
    rng = np.random.default_rng(0)
    F = 0.05 * rng.standard_normal((3, 6, 6))
    e = kf.transition_matrix(F, 1.0, "expm")
    a = np.linalg.norm(F, ord=2, axis=(-2, -1)).max()
    for order in (2, 4, 8):
        t = kf.transition_matrix(F, 1.0, "taylor", order)
        # remainder of the exponential series: <= a^(p+1)/(p+1)! e^a


        bound = a ** (order + 1) / math.factorial(order + 1) * math.exp(a)
        assert np.abs(t - e).max() <= bound
    # nilpotent F (double integrator): the order-1 series is exact
    N = np.zeros((1, 2, 2))
    N[0, 0, 1] = 1.0
    np.testing.assert_array_equal(kf.transition_matrix(N, 2.0, "taylor", 1)[0], [[1.0, 2.0], [0.0, 1.0]])


def test_predict_covariance_matches_formula():
    rng = np.random.default_rng(1)
    x, P, H, R, y = random_problem(rng, 2, 4, 2)
    Phi = np.eye(4) + 0.1 * rng.standard_normal((2, 4, 4))
    Q = rng.uniform(0, 1, 4)
    out = kf.predict_covariance(P, Phi, Q)
    for b in range(2):
        np.testing.assert_allclose(out[b], Phi[b] @ P[b] @ Phi[b].T + np.diag(Q), rtol=1e-12)


def test_stopping_sizes_are_unit_free():
    P = np.diag([4.0, 1e-6])[None]
    L = np.linalg.cholesky(P)
    dx = np.array([[2.0, 1e-3]])  # one prior sigma in each coordinate
    dz = np.linalg.solve(L, dx[..., None])[..., 0]
    H = np.array([[[0.0, 1.0]]])
    R = np.array([[1e-6]])
    Hw = H @ L / np.sqrt(R)[..., None]
    assert kf._increment_size(dz, Hw, L, P, "prior")[0] == pytest.approx(np.sqrt(2.0))
    assert kf._increment_size(dz, Hw, L, P, "scaled")[0] == pytest.approx(1.0)
    # posterior information adds (H dx)^2 / R = 1
    assert kf._increment_size(dz, Hw, L, P, "mahalanobis")[0] == pytest.approx(np.sqrt(3.0))
    assert kf._increment_size(dz, Hw, L, P, "raw")[0] == pytest.approx(np.hypot(2.0, 1e-3))


def test_iekf_nis_equals_the_ekf_nis():
    rng = np.random.default_rng(11)
    x, P, H, R, y = random_problem(rng, 5, 6, 4)
    e = kf.ekf_update(x, P, y, linear_measure(H), R, np.arange(5))
    i = kf.iekf_update(x, P, y, linear_measure(H), R, np.arange(5))
    np.testing.assert_allclose(i.nis, e.nis, rtol=1e-9)
