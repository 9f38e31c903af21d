"""Per-feature chi-square gating (filters/gating.py) on linear-Gaussian data."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from stereopose_mc.core import kalman as kf
from stereopose_mc.filters import gating

F, C, n = 6, 4, 5


def linear_problem(b: int, seed: int = 0):
    """Random linear measurements of b trials: y = H x_true + v, x_true ~ N(x, P), v ~ N(0, R)."""
    rng = np.random.default_rng(seed)
    H = rng.normal(size=(b, F * C, n))
    A = rng.normal(size=(b, n, n))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)
    R = rng.uniform(0.5, 2.0, size=F * C)
    x = rng.normal(size=(b, n))
    x_true = x + np.einsum("bij,bj->bi", np.linalg.cholesky(P), rng.normal(size=(b, n)))
    y = np.einsum("bij,bj->bi", H, x_true) + np.sqrt(R) * rng.normal(size=(b, F * C))
    return rng, H, P, R, x, y


def test_blocks_are_the_diagonal_blocks_of_S():
    _, H, P, R, _, _ = linear_problem(3)
    S = kf.innovation_covariance(P, H, np.broadcast_to(R, (3, F * C)).copy())
    blocks = gating.linearized_blocks(H, P, R, F, C)
    for f in range(F):
        np.testing.assert_allclose(blocks[:, f], S[:, f * C : (f + 1) * C, f * C : (f + 1) * C], rtol=1e-12)


def test_blocks_equal_the_dense_product():
    """Row-sparse H as in the filters (each feature: 13 shared columns and its own 3): the same blocks as the
    dense product (an independent einsum)."""
    rng = np.random.default_rng(3)
    b, nf, c = 4, 5, 8
    nn = 13 + 3 * nf + 2
    A = rng.normal(size=(b, nn, nn))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(nn)
    R = rng.uniform(0.5, 2.0, size=nf * c + 3)  # 3 pseudo rows after the features' (not gated)
    H = np.zeros((b, nf * c + 3, nn))
    for f in range(nf):
        cols = np.r_[np.arange(13), 13 + 3 * f + np.arange(3)]
        H[:, f * c : (f + 1) * c, cols] = rng.normal(size=(b, c, 16))
    H[:, nf * c :] = rng.normal(size=(b, 3, nn))
    H[0, 0, 5] = 0.0  # an exact zero by chance in one trial: the column is still used (other trials have it)
    Hf = H[:, : nf * c].reshape(b, nf, c, nn)
    dense = np.einsum("bfcn,bnm,bfdm->bfcd", Hf, P, Hf)
    dense[..., np.arange(c), np.arange(c)] += R[: nf * c].reshape(nf, c)
    np.testing.assert_allclose(gating.linearized_blocks(H, P, R, nf, c), dense, rtol=1e-12, atol=1e-12)


def test_threshold_is_the_chi_square_quantile():
    # chi2(4) has survival function exp(-t/2)(1 + t/2): solve it for 1 - p = 1e-3 by hand (bisection)
    lo, hi = 0.0, 100.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.exp(-mid / 2) * (1 + mid / 2) > 1e-3 else (lo, mid)
    assert gating.threshold(0.999, 4) == pytest.approx(lo, rel=1e-9)


@pytest.mark.parametrize("p", [0.9, 0.99])
def test_false_rejection_rate_on_noise_only_data(p):
    b = 5000
    _, H, P, R, x, y = linear_problem(b, seed=1)
    hx = np.einsum("bij,bj->bi", H, x)
    d2 = gating.distances2(y - hx, gating.linearized_blocks(H, P, R, F, C))
    keep, rejected = gating.gate(d2, p, C)
    rate = 1.0 - keep.mean()
    sd = np.sqrt((1 - p) * p / keep.size)
    assert abs(rate - (1 - p)) < 4 * sd, (rate, 1 - p)
    assert rejected.sum() == (~keep).sum()
    # the distances themselves are chi-square with C degrees of freedom
    assert stats.kstest(d2.ravel(), stats.chi2(C).cdf).pvalue > 1e-3


def test_planted_outliers_are_rejected():
    b = 2000
    rng, H, P, R, x, y = linear_problem(b, seed=2)
    hx = np.einsum("bij,bj->bi", H, x)
    S = gating.linearized_blocks(H, P, R, F, C)
    planted = rng.random((b, F)) < 0.05
    # an outlier 30 standard deviations away along a random direction of its S_f
    d = rng.normal(size=(b, F, C))
    d *= 30.0 / np.linalg.norm(d, axis=-1, keepdims=True)
    off = np.einsum("bfij,bfj->bfi", np.linalg.cholesky(S), d) * planted[..., None]
    nu = y - hx + off.reshape(b, F * C)
    keep, rejected = gating.gate(gating.distances2(nu, S), 0.999, C)
    assert not keep[planted].any()  # every planted outlier rejected
    false_rate = 1.0 - keep[~planted].mean()
    assert false_rate < 1e-3 + 4 * np.sqrt(1e-3 / (~planted).sum())
    # dropped features are not counted as rejected
    prior = ~planted
    keep2, rej2 = gating.gate(gating.distances2(nu, S), 0.999, C, prior)
    assert not keep2[planted].any() and rej2.sum() == (prior & ~keep2).sum()


def _linear_measure(H_all):
    def measure(x, rows, jac=True):
        H = H_all[rows]
        return np.einsum("bij,bj->bi", H, x), (H if jac else None)

    return measure


@pytest.mark.parametrize("kind", ["ekf", "iekf"])
def test_masked_update_equals_the_update_without_those_rows(kind):
    b = 4
    rng, H, P, R, x, y = linear_problem(b, seed=3)
    keep = rng.random((b, F)) < 0.6
    keep[:, 0] = True
    rows = np.arange(b)
    measure = gating.masked_measure(_linear_measure(H), y, rows, keep, C)
    Rb = np.broadcast_to(R, (b, F * C))
    if kind == "ekf":
        u = kf.ekf_update(x, P, y, measure, Rb, rows)
    else:
        u = kf.iekf_update(x, P, y, measure, Rb, rows, tol=1e-12, max_iter=3, step_control="none")
    for i in range(b):
        sel = np.repeat(keep[i], C)
        ref = kf.ekf_update(x[i : i + 1], P[i : i + 1], y[i : i + 1, sel],
                            _linear_measure(H[i : i + 1, sel]), R[sel][None], np.array([0]))  # fmt: skip
        np.testing.assert_allclose(u.x[i], ref.x[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(u.P[i], ref.P[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(u.nis[i], ref.nis[0], rtol=1e-9)


def test_chi2_median_is_the_quantile():
    for dof in (1, 2, 4, 8):
        assert gating.chi2_median(dof) == pytest.approx(stats.chi2.median(dof), rel=1e-12)


def test_robust_gate_leaves_a_consistent_filter_alone():
    """Innovations drawn from the claimed S: no trial meets the lock-out condition, so the robust gate is the
    plain gate and the prior is not inflated."""
    b = 2000
    _, H, P, R, x, y = linear_problem(b, seed=4)
    d2 = gating.distances2(y - np.einsum("bij,bj->bi", H, x), gating.linearized_blocks(H, P, R, F, C))
    keep, rejected, lam = gating.robust_gate(d2, 0.999, C)
    k0, r0 = gating.gate(d2, 0.999, C)
    np.testing.assert_array_equal(keep, k0)
    np.testing.assert_array_equal(rejected, r0)
    np.testing.assert_array_equal(lam, np.ones(b))


def test_robust_gate_recovers_the_scale_of_an_overconfident_prior():
    """A filter whose P is 50x too small (the truth drawn from 50 P): the plain gate rejects most features of most
    trials (a lock-out); the robust gate estimates lam ~ 50 x (the HPH^T share of S) from the median, keeps the
    features (one outlier of six per trial is still rejected), and ``inflated`` scales P by it."""
    rng = np.random.default_rng(9)
    b, s2 = 400, 50.0
    H = rng.normal(size=(b, F * C, n))
    A = rng.normal(size=(b, n, n))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)
    R = np.full(F * C, 1e-3)  # R small against H P H^T: S scales as P does
    x = rng.normal(size=(b, n))
    x_true = x + np.einsum("bij,bj->bi", np.linalg.cholesky(s2 * P), rng.normal(size=(b, n)))
    y = np.einsum("bij,bj->bi", H, x_true) + np.sqrt(R) * rng.normal(size=(b, F * C))
    y[:, :C] += 1e3  # feature 0 of every trial: an outlier
    d2 = gating.distances2(y - np.einsum("bij,bj->bi", H, x), gating.linearized_blocks(H, P, R, F, C))
    _, r_plain = gating.gate(d2, 0.999, C)
    keep, rejected, lam = gating.robust_gate(d2, 0.999, C)
    locked = r_plain >= gating.LOCKOUT_FRACTION * F
    assert locked.mean() > 0.5
    assert np.median(lam[locked]) == pytest.approx(s2, rel=0.35)
    assert np.all(~keep[locked, 0])  # the outlier stays out
    assert np.mean(keep[locked, 1:]) > 0.9
    _, _, lam_off = gating.robust_gate(d2, 0.999, C, inflate=False)
    np.testing.assert_array_equal(lam_off, np.ones(b))
    np.testing.assert_allclose(gating.inflated(P, lam)[locked], P[locked] * lam[locked, None, None])
