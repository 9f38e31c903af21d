"""The pseudo-measurement's second-order variance (core.inertia): finite differences and sampling."""

from __future__ import annotations

import numpy as np
import pytest

from stereopose_mc.core import quaternion as qt
from stereopose_mc.core import state as st
from stereopose_mc.core import dynamics, jacobians
from stereopose_mc.core.dynamics import MU_EARTH
from stereopose_mc.core.inertia import (euler_coefficients, h_pseudo, pseudo_second_order_variance,
                                        rate_second_order_variance)  # fmt: skip
from stereopose_mc.core.jacobians import H_pseudo

DEG = np.pi / 180


def _state(k=(np.log(0.83), np.log(1.0 / 1.083))) -> np.ndarray:
    q = qt.normalize(np.array([0.9, 0.2, -0.3, 0.25]))
    pts = np.array([[1.5, 0, 0], [0, 1.5, 0], [0, 0, 1.5]])
    return st.assemble([10.0, 60.0, 10.0], [0.01, -0.02, -0.01], np.array([-0.1, -0.1, 0.034]) * DEG, q, pts,
                       np.asarray(k))  # fmt: skip


def test_euler_coefficients_match_the_gyroscopic_term_and_finite_differences():
    k = np.array([0.3, -0.2])
    c, dc, ddc = euler_coefficients(k)
    inertia = st.inertia_diag(k)
    w = np.array([0.01, -0.02, 0.03])
    gyro = np.cross(w, inertia * w) / inertia
    np.testing.assert_allclose(c * np.array([w[1] * w[2], w[2] * w[0], w[0] * w[1]]), gyro, rtol=1e-12)
    h = 1e-6
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        fd = (euler_coefficients(k + e)[0] - euler_coefficients(k - e)[0]) / (2 * h)
        np.testing.assert_allclose(dc[:, j], fd, rtol=1e-7, atol=1e-10)
        fd2 = (euler_coefficients(k + e)[1] - euler_coefficients(k - e)[1]) / (2 * h)
        np.testing.assert_allclose(ddc[:, :, j], fd2, rtol=1e-7, atol=1e-10)


@pytest.mark.parametrize(("sigma_w_deg", "sigma_k", "rtol"), [(1.0, 0.0, 0.02), (0.1, 0.0, 0.02), (1.0, 0.02, 0.08),
                                                             (0.1, 0.02, 0.08)])  # fmt: skip
def test_second_order_variance_matches_sampled_linearization_error(sigma_w_deg, sigma_k, rtol):
    """Draw correlated omega and k errors, evaluate h_pseudo's exact change minus its Jacobian's prediction: the
    sampled variance of that remainder is what the formula gives (4e5 draws: about 1 % sampling error). The
    formula is exact for the part quadratic in omega; with k uncertain it keeps the terms of lowest order (the
    bound of 8 % at sigma_k = 0.02; at 0.2 it is low by up to 1.6x, docs/filters.md)."""
    x = _state()
    cov, xs = _sampled(x, sigma_w_deg, sigma_k, 7)
    alpha = np.array([1e-6, -2e-6, 5e-7])
    nu_dot, nu_ddot = 1.1e-3, 1e-9
    H = H_pseudo(x[None], alpha[None], nu_dot, nu_ddot)[0]
    h0 = h_pseudo(x[None], alpha[None], nu_dot, nu_ddot)
    rem = h_pseudo(xs, np.broadcast_to(alpha, (xs.shape[0], 3)), nu_dot, nu_ddot) - h0 - (xs - x) @ H.T
    got = pseudo_second_order_variance(x, cov[:3, :3], cov[3:, 3:], cov[3:, :3], nu_dot)
    np.testing.assert_allclose(rem.var(axis=0), got, rtol=rtol)


def _sampled(x: np.ndarray, sigma_w_deg: float, sigma_k: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``(cov, xs)``: a random correlation of omega's and k's errors at these sigmas, and 4e5 states ``x`` plus draws
    from it (about 1 % sampling error on a variance)."""
    rng = np.random.default_rng(seed)
    corr = _corr(rng.normal(size=(5, 5)))
    sig = np.r_[[sigma_w_deg * DEG] * 3, [sigma_k] * 2]
    cov = sig[:, None] * corr * sig[None, :]
    d = rng.multivariate_normal(np.zeros(5), cov, size=400_000)
    xs = np.broadcast_to(x, (d.shape[0], x.size)).copy()
    xs[:, st.OMEGA] += d[:, :3]
    xs[:, -2:] += d[:, 3:]
    return cov, xs


def _corr(A: np.ndarray) -> np.ndarray:
    C = A @ A.T
    s = np.sqrt(np.diag(C))
    return C / s[:, None] / s[None, :]


def test_second_order_variance_vanishes_without_uncertainty_and_is_batched():
    x = np.stack([_state(), _state((0.1, 0.2))])
    z3, z2, z23 = np.zeros((2, 3, 3)), np.zeros((2, 2, 2)), np.zeros((2, 2, 3))
    np.testing.assert_array_equal(pseudo_second_order_variance(x, z3, z2, z23, 1e-3), np.zeros((2, 3)))
    P = np.eye(3) * 1e-6
    one = pseudo_second_order_variance(x[1], P, np.eye(2) * 0.01, np.zeros((2, 3)), 1e-3)
    both = pseudo_second_order_variance(x, np.stack([P, P]), np.stack([np.eye(2) * 0.01] * 2), z23, 1e-3)
    np.testing.assert_allclose(both[1], one, rtol=1e-14)


@pytest.mark.parametrize(("sigma_w_deg", "sigma_k"), [(1.0, 0.0), (0.1, 0.0), (1.0, 0.02), (0.1, 0.02)])
def test_rate_second_order_variance_bounds_the_sampled_remainder_of_the_dynamics(sigma_w_deg, sigma_k):
    """The rate's dynamics ``omega' = f(x)`` (``core.dynamics.f``) beyond its Jacobian (``jacobians.F``) under sampled
    omega and k errors: per axis of ``L`` the bound covers the sampled variance (up to the pseudo formula's own
    accuracy, 8 % with k uncertain, test above) and exceeds it by at most the Cauchy-Schwarz factor 3 (here by
    2.1-2.4: the three rows' remainders are of one size, and their correlations are not formed)."""
    x = _state()
    cov, xs = _sampled(x, sigma_w_deg, sigma_k, 11)
    r_L, nu_dot, nu_ddot = 7.0e6, 1.1e-3, 1e-9
    F = jacobians.F(x[None], r_L, nu_dot, nu_ddot, MU_EARTH)[0]
    rem = (dynamics.f(xs, r_L, nu_dot, nu_ddot) - dynamics.f(x, r_L, nu_dot, nu_ddot) - (xs - x) @ F.T)[:, st.OMEGA]
    sampled = rem.var(axis=0)
    got = rate_second_order_variance(x, cov[:3, :3], cov[3:, 3:], cov[3:, :3], nu_dot)
    assert (got >= 0.92 * sampled).all(), (got, sampled)
    assert (got <= 3.0 * 1.03 * sampled).all(), (got, sampled)


def test_rate_second_order_variance_is_the_pseudo_rows_at_the_identity_attitude():
    """With ``D = I`` the rows of ``T`` are the axes of ``L``: the bound is each row's variance, exactly."""
    x = _state()
    x[st.QUAT] = [1.0, 0.0, 0.0, 0.0]
    P_ww, P_kk, P_kw = np.diag([2.0, 1.0, 3.0]) * 1e-4, np.diag([0.04, 0.09]), np.full((2, 3), 1e-4)
    np.testing.assert_allclose(rate_second_order_variance(x, P_ww, P_kk, P_kw, 1e-3),
                               pseudo_second_order_variance(x, P_ww, P_kk, P_kw, 1e-3), rtol=1e-15)  # fmt: skip
    assert (rate_second_order_variance(x, P_ww * 0, P_kk * 0, P_kw * 0, 1e-3) == 0).all()
