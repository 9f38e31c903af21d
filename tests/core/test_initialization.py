"""Triangulation and rigid-body flow fit: exact on noise-free truth, statistically right on noisy truth."""

import numpy as np
from scipy import stats

from stereopose_mc.core import camera, initialization as ini, quaternion as qt, state as st

RNG = np.random.default_rng(3)
B_LINE = 1.0


def truth_state():
    pts = np.array([[1.5, 0, 0], [0, 1.5, 0], [0, 0, 1.5], [-1.06, -1.06, 0], [0, -1.06, -1.06]])
    return st.assemble([10.0, 60.0, 10.0], [0.01, -0.0225, -0.01], np.deg2rad([-0.1, -0.1, 0.034]),
                       qt.normalize([0.9, 0.1, -0.2, 0.3]), pts, [-0.186, -0.08])  # fmt: skip


def test_triangulation_and_flow_fit_are_exact_on_noise_free_truth():
    x = truth_state()
    for focal in (1.0, 800.0):
        y = camera.h_features(x, B_LINE, False, focal)
        rho_i, rho_dot_i = ini.triangulate(y, B_LINE, focal)
        true_p, true_v = camera.feature_kinematics(x)
        np.testing.assert_allclose(rho_i, true_p, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(rho_dot_i, true_v, rtol=1e-9, atol=1e-14)
    C = ini.point_covariance(rho_i, rho_dot_i, B_LINE, np.full(8, 1e-10))
    c, v_c, w, cov = ini.rigid_fit(rho_i, rho_dot_i, C)
    np.testing.assert_allclose(c, true_p.mean(0), rtol=1e-12)
    np.testing.assert_allclose(w, x[st.OMEGA], rtol=1e-8, atol=1e-15)
    # the centroid's velocity: rho_dot_0 + omega x (c - rho_0)
    np.testing.assert_allclose(v_c, x[st.RHO_DOT] + np.cross(x[st.OMEGA], c - x[st.RHO]), rtol=1e-9, atol=1e-14)


def test_noisy_fit_errors_match_their_covariance():
    """2000 noisy frames: the NEES of each point and of [v_c, omega] average their dof."""
    x = truth_state()
    sig = 1e-5
    M = 2000
    y = camera.h_features(x, B_LINE) + sig * RNG.standard_normal((M, 5, 8))
    rho_i, rho_dot_i = ini.triangulate(y, B_LINE)
    C = ini.point_covariance(rho_i, rho_dot_i, B_LINE, np.full(8, sig**2))
    true_p, true_v = camera.feature_kinematics(x)
    e = np.concatenate([rho_i - true_p, rho_dot_i - true_v], -1)  # (M, 5, 6)
    nees = np.einsum("...i,...i->...", e, np.linalg.solve(C, e[..., None])[..., 0])
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], M * 6) / M
    assert np.all((nees.mean(0) > lo) & (nees.mean(0) < hi)), nees.mean(0)
    c, v_c, w, cov = ini.rigid_fit(rho_i, rho_dot_i, C)
    ref_v = x[st.RHO_DOT] + np.cross(x[st.OMEGA], c - x[st.RHO])
    e2 = np.concatenate([v_c - ref_v, w - x[st.OMEGA]], -1)
    n2 = np.einsum("...i,...i->...", e2, np.linalg.solve(cov, e2[..., None])[..., 0])
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], M * 6) / M
    assert lo < n2.mean() < hi, n2.mean()  # the lever arms' noise is in the weights (errors in the variables)


def test_the_fit_weights_the_lever_arms_errors_where_stereo_depth_is_poor():
    """configs/mission-mesh-dispersed.yaml's camera (f = 3822 px, b = 0.5 m, 0.3 px, 0.1 px/s) at 60 m: each point's
    depth is known to about 0.8 m, as large as the lever arms, so the rate's residuals are dominated by
    ``omega x d rho_i``. The errors-in-variables weights widen the fit's claimed rate covariance and cut its NEES by
    more than 10x against the velocity-only weights; the rate stays biased toward 0 (regression dilution: noisy
    lever arms), which no weighting removes, so its NEES stays above its 3 dof: on such a rig the prior start and
    the filter's iterated first update are the better start (docs/filters.md, Initial estimate)."""
    rng = np.random.default_rng(5)
    f, b, R8 = 3822.0, 0.5, np.array([0.3**2] * 4 + [0.1**2] * 4)
    pts = rng.uniform(-1, 1, (24, 3)) * [0.5, 1.0, 1.5]
    x = st.assemble([10.0, 60.0, 10.0], [0.01, -0.0225, -0.01], np.deg2rad([1.2, -1.0, 1.1]),
                    qt.normalize([0.9, 0.1, -0.2, 0.3]), pts, [0.26, 0.69])  # fmt: skip
    y = camera.h_features(x, b, False, f) + np.sqrt(R8) * rng.standard_normal((500, 24, 8))
    rho_i, rho_dot_i = ini.triangulate(y, b, f)
    C = ini.point_covariance(rho_i, rho_dot_i, b, R8, f)
    assert 0.7 < (rho_i - camera.feature_kinematics(x)[0])[..., 1].std() < 0.9  # depth sigma ~0.8 m
    nees = {}
    for its in (0, ini.FIT_ITERATIONS):
        _, _, w, cov = ini.rigid_fit(rho_i, rho_dot_i, C, its)
        e = w - x[st.OMEGA]
        nees[its] = np.einsum("...i,...i->...", e, np.linalg.solve(cov[..., 3:, 3:], e[..., None])[..., 0]).mean()
        if its:
            assert (np.diagonal(cov[..., 3:, 3:], axis1=-2, axis2=-1) > np.diagonal(plain, axis1=-2, axis2=-1)).all()
        plain = cov[..., 3:, 3:]
    assert nees[ini.FIT_ITERATIONS] < nees[0] / 10
    assert nees[ini.FIT_ITERATIONS] > 3 * 10
