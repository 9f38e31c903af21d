"""The error state: chart, its Jacobians, the centre-of-mass gauge and the NEES degrees of freedom."""

import numpy as np
import pytest
from scipy import stats

from stereopose_mc.core import camera, errorstate as es, quaternion as qt, state as st

from scenarios import random_states  # noqa: E402

RNG = np.random.default_rng(7)


def random_state(B=4, N=3):
    return random_states(RNG, B, N)


def test_chart_and_local_are_inverse():
    x = random_state()
    eps = 0.3 * RNG.standard_normal((4, x.shape[-1] - 1))
    np.testing.assert_allclose(es.local(x, es.chart(x, eps)), eps, atol=1e-12)
    # the attitude error is the rotation between the two attitudes: 2 atan(|a|/2) by the Gibbs chart
    xe = es.chart(x, eps)
    ang = qt.error_angle(xe[:, st.QUAT], x[:, st.QUAT])
    np.testing.assert_allclose(ang, 2 * np.arctan(np.linalg.norm(eps[:, es.ATT], axis=-1) / 2), atol=1e-12)


def test_chart_jacobian_matches_finite_differences():
    x = random_state()
    eps = 0.2 * RNG.standard_normal((4, x.shape[-1] - 1))
    S = es.chart_jacobian(x, eps)
    h = 1e-6
    for j in range(eps.shape[-1]):
        d = np.zeros_like(eps)
        d[:, j] = h
        fd = (es.chart(x, eps + d) - es.chart(x, eps - d)) / (2 * h)
        np.testing.assert_allclose(S[..., j], fd, atol=1e-8)


def test_error_map_inverts_the_chart_to_first_order():
    x = random_state()
    T, S = es.error_map(x), es.chart_jacobian(x)
    np.testing.assert_allclose(T @ S, np.broadcast_to(np.eye(x.shape[-1] - 1), T.shape[:-2] + (x.shape[-1] - 1,) * 2),
                               atol=1e-12)  # fmt: skip
    e = 1e-7 * RNG.standard_normal((4, x.shape[-1] - 1))
    np.testing.assert_allclose(np.einsum("bij,bj->bi", T, es.chart(x, e) - x), e, rtol=1e-5, atol=1e-15)


def test_centre_of_mass_gauge_leaves_every_image_unchanged():
    """Moving along the gauge basis changes the images only at second order (exactly zero for positions)."""
    x = random_state()
    G = es.gauge_basis(x)
    for j in range(3):
        for t in (1e-3, 1e-4):
            y0 = camera.h_features(x, 1.0)
            y1 = camera.h_features(es.chart(x, t * G[..., j]), 1.0)
            assert np.max(np.abs(y1 - y0)) < 1e-3 * t  # first order would be ~ t / 40
    # and a generic direction of the same size does change them at first order
    d = RNG.standard_normal(G.shape[:-1])
    assert np.max(np.abs(camera.h_features(es.chart(x, 1e-4 * d), 1.0) - camera.h_features(x, 1.0))) > 1e-7


def test_nees_has_the_documented_degrees_of_freedom():
    """Errors drawn from the claimed covariance: each NEES averages its dof (chi-square)."""
    N, M = 2, 4000
    x = np.repeat(random_state(1, N), M, axis=0)
    ne = x.shape[-1] - 1
    A = RNG.standard_normal((ne, ne))
    P = A @ A.T / ne + 0.1 * np.eye(ne)
    eps = RNG.standard_normal((M, ne)) @ np.linalg.cholesky(P).T
    v = es.nees_all(eps, np.broadcast_to(P, (M, ne, ne)), x)
    dof = es.nees_dof(x.shape[-1])
    assert dof["nees"] == 13 + 3 * N + 2 - 1 and dof["nees_gauge"] == dof["nees"] - 3
    assert dof["nees_attitude"] == 3 and dof["nees_feature_points"] == 3 * N and dof["nees_k"] == 2
    for k, d in dof.items():
        lo, hi = stats.chi2.ppf([0.0005, 0.9995], M * d) / M
        assert lo < v[k].mean() < hi, (k, v[k].mean(), d)


def test_full_state_covariance_maps_to_the_error_state():
    """NEES of a quaternion-state error with its covariance equals the error-state NEES."""
    x = random_state(1, 2)
    n = x.shape[-1]
    S = es.chart_jacobian(x)[0]
    A = RNG.standard_normal((n - 1, n - 1))
    Pe = A @ A.T + np.eye(n - 1)
    u = np.zeros(n)
    u[st.QUAT] = x[0, st.QUAT]
    Pfull = S @ Pe @ S.T + 0.3 * np.outer(u, u)  # variance along the quaternion's norm: no attitude error
    e = 1e-6 * RNG.standard_normal(n - 1)
    x_hat = es.chart(x, e[None])
    np.testing.assert_allclose(es.to_error_covariance(x_hat, Pfull[None])[0], Pe, rtol=1e-4)
    np.testing.assert_allclose(es.estimation_error(x_hat, x[0]), e[None], rtol=1e-5, atol=1e-16)


@pytest.mark.parametrize("bad", [np.nan, -1.0])
def test_nees_is_nan_for_a_broken_covariance(bad):
    P = np.eye(3)[None].copy()
    P[0, 0, 0] = bad
    assert np.isnan(es._nees(np.ones((1, 3)), P)[0])


@pytest.mark.parametrize("size", [1e-3, 0.5, 3.0])
def test_gauge_act_changes_no_image_and_its_jacobian_matches_finite_differences(size):
    x = random_state()
    d = size * RNG.standard_normal((4, 3))
    y = es.gauge_act(x, d)
    np.testing.assert_allclose(camera.h_features(y, 1.0), camera.h_features(x, 1.0), rtol=0, atol=1e-13)
    np.testing.assert_allclose(y[:, st.QUAT], x[:, st.QUAT])
    np.testing.assert_allclose(es.gauge_act(y, -d), x, atol=1e-12)  # the inverse move
    J = es.gauge_act_jacobian(x, d)
    ne = x.shape[-1] - 1
    h = 1e-6
    for j in range(ne):
        e = np.zeros((4, ne))
        e[:, j] = h
        fd = (es.local(y, es.gauge_act(es.chart(x, e), d)) - es.local(y, es.gauge_act(es.chart(x, -e), d))) / (2 * h)
        np.testing.assert_allclose(J[..., j], fd, atol=1e-8)


def test_gauge_projected_nees_is_chi_square_however_far_along_the_gauge_the_estimate_is():
    """Truths = estimate [+] N(0, P) in the aligned chart; then the estimates moved 0.5-1 m along their gauge orbit.

    The gauge-projected NEES of the aligned chart (core.aligned.nees_report) averages its
    n - 4 dof wherever the estimate sits on its orbit; the linear projection of the
    attitude chart (nees_all, the same covariance mapped) does not: with a 3 deg attitude
    error the curvature a x (D d) is several sigma of the tightly known directions.
    """
    from stereopose_mc.core import aligned

    M = 3000
    x_hat = np.repeat(random_state(1, 2), M, axis=0)
    ne = x_hat.shape[-1] - 1
    sig = np.full(ne, 1e-3)
    sig[aligned.DELTA] = 0.05  # a weakly known attitude
    P = np.broadcast_to(np.diag(sig**2), (M, ne, ne))
    x_true = aligned.chart(x_hat, RNG.standard_normal((M, ne)) * sig)
    d = RNG.uniform(0.5, 1.0, (M, 1)) * qt.normalize(RNG.standard_normal((M, 3)))
    moved = es.gauge_act(x_hat, d)  # in the aligned chart a pure shift of every e_P: P is carried unchanged
    dof = es.nees_dof(x_hat.shape[-1])["nees_gauge"]
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], M * dof) / M
    for est in (x_hat, moved):
        g = aligned.nees_report(est, P, x_true)["nees_gauge"]
        assert lo < g.mean() < hi, (g.mean(), dof)
    linear = es.nees_all(es.estimation_error(moved, x_true), aligned.to_attitude_chart(moved, P), moved)["nees_gauge"]
    assert linear.mean() > 5 * dof


@pytest.mark.parametrize("size", [0.01, 0.5, 3.0])
def test_aligned_gauge_projection_does_not_see_a_move_along_the_gauge(size):
    """z = V^T local_aligned(x_hat, x_true) is the same for x_hat and gauge_act(x_hat, d), any d (exactly)."""
    from stereopose_mc.core import aligned

    x_true = random_state()
    x_hat = es.chart(x_true, 0.05 * RNG.standard_normal((4, x_true.shape[-1] - 1)))
    V = aligned.gauge_complement(x_true.shape[-1])
    z0 = aligned.local(x_hat, x_true) @ V
    z1 = aligned.local(es.gauge_act(x_hat, size * RNG.standard_normal((4, 3))), x_true) @ V
    np.testing.assert_allclose(z1, z0, rtol=0, atol=1e-12 * (1 + size))
    # and the truth moved along its own orbit, likewise
    z2 = aligned.local(x_hat, es.gauge_act(x_true, size * RNG.standard_normal((4, 3)))) @ V
    np.testing.assert_allclose(z2, z0, rtol=0, atol=1e-12 * (1 + size))
