"""Compiled model kernels (core/kernels/model.py) against their numpy twins and finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st_h

from stereopose_mc.core import camera, dynamics, inertia, jacobians, kalman, state as st
from stereopose_mc.core.kernels import model as km
from stereopose_mc.core.orbit import MU_EARTH

RL, ND, NDD = 6.9e6, 1.1e-3, 2.0e-9  # an eccentric leader's r_L, nu', nu''


def states(B=5, N=5, seed=0):
    """Random but physical states: target ~30 m ahead (y > 0), rates ~0.01 rad/s, points ~2 m."""
    rng = np.random.default_rng(seed)
    x = np.empty((B, st.size(N)))
    x[:, 0:3] = [3.0, 30.0, -2.0] + rng.normal(size=(B, 3))
    x[:, 3:6] = 0.01 * rng.normal(size=(B, 3))
    x[:, 6:9] = 0.02 * rng.normal(size=(B, 3))
    x[:, 9:13] = rng.normal(size=(B, 4)) * 1.1  # not unit: D(q) normalizes
    x[:, 13 : 13 + 3 * N] = 2.0 * rng.normal(size=(B, 3 * N))
    x[:, -2:] = 0.3 * rng.normal(size=(B, 2))
    return x


def rel(a, b):
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


def test_f_matches_numpy():
    x = states()
    assert rel(km.f_batch(x, RL, ND, NDD, MU_EARTH), dynamics.f(x, RL, ND, NDD, MU_EARTH)) < 1e-12


def test_propagate_matches_numpy_rk4():
    from stereopose_mc.core.orbit import Orbit, leader_kinematics

    orbit = Orbit(a=7.0e6, e=0.05, i=0.9, raan=0.1, argp=0.2, nu0=0.3)
    x = states()
    for substeps in (1, 2):
        h = 1.0 / substeps
        lk = leader_kinematics(orbit, 5.0 + 0.5 * h * np.arange(2 * substeps + 1))
        got = km.propagate_batch(x, lk.r, lk.nu_dot, lk.nu_ddot, h, orbit.mu, substeps, False)
        want = dynamics.propagate(x, 5.0, 1.0, orbit, substeps)
        assert rel(got, want) < 1e-13
        normed = km.propagate_batch(x, lk.r, lk.nu_dot, lk.nu_ddot, h, orbit.mu, substeps, True)
        assert np.allclose(np.linalg.norm(normed[:, st.QUAT], axis=-1), 1.0, rtol=0, atol=1e-15)


def test_F_matches_numpy_and_finite_differences():
    x = states()
    F = km.F_batch(x, RL, ND, NDD, MU_EARTH)
    assert rel(F, jacobians.F(x, RL, ND, NDD, MU_EARTH)) < 1e-12
    n = x.shape[-1]
    eps = 1e-6 * np.maximum(np.abs(x[0]), 1e-2)
    fd = np.empty((n, n))
    for j in range(n):
        d = np.zeros(n)
        d[j] = eps[j]
        fd[:, j] = (km.f_batch((x[0] + d)[None], RL, ND, NDD, MU_EARTH)[0]
                    - km.f_batch((x[0] - d)[None], RL, ND, NDD, MU_EARTH)[0]) / (2 * eps[j])  # fmt: skip
    assert np.allclose(F[0], fd, rtol=1e-5, atol=1e-9 * np.max(np.abs(F[0])))
    # the block structure the kernels rely on: only rows 0-12 and columns [0..12, k] are non-zero
    mask = np.zeros((n, n), bool)
    mask[:13, :13] = mask[:13, -2:] = True
    assert np.all(F[:, ~mask] == 0.0) and np.all(jacobians.F(x, RL, ND, NDD, MU_EARTH)[:, ~mask] == 0.0)
    # and within it two diagonal blocks (the transition's Horner products and the covariance predict run on them):
    # the translation (rows 0-5) sees columns 0-5 only, the rotation (rows 6-12) columns 6-12 and k
    for Fb in (F, jacobians.F(x, RL, ND, NDD, MU_EARTH), fd[None]):
        assert np.all(Fb[:, :6, 6:] == 0.0) and np.all(Fb[:, 6:13, :6] == 0.0) and np.all(Fb[:, 6:13, 13:-2] == 0.0)


def test_transition_blocks_over_random_states_equal_the_dense_series():
    """``transition_reduced_batch`` (Horner on F's two blocks) against the dense Taylor series of the whole ``F dt``
    over states far and near (fast spin, large k, a long step): the same to a few ulps, and zero off the blocks."""
    for seed in range(5):
        x = states(B=6, N=5, seed=seed)
        x[:, 6:9] *= 10.0 ** (seed - 2)
        x[:, -2:] *= 3.0
        Fd = jacobians.F(x, RL, ND, NDD, MU_EARTH)
        for dt, order in ((0.5, 3), (2.0, 4), (10.0, 6)):
            T = km.transition_reduced_batch(km.F_reduced_batch(x, RL, ND, NDD, MU_EARTH), dt, order)
            Phi = km.dense_transition(T, x.shape[1])
            assert rel(Phi, kalman.transition_matrix(Fd, dt, "taylor", order)) < 1e-14
            assert np.all(T[:, :6, 6:] == 0.0) and np.all(T[:, 6:13, :6] == 0.0)


@pytest.mark.parametrize("order", [2, 4, 6])
def test_transition_and_covariance_predict_match_dense(order):
    x = states(B=4, N=7)
    B, n = x.shape
    Fd = jacobians.F(x, RL, ND, NDD, MU_EARTH)
    T = km.transition_reduced_batch(km.F_reduced_batch(x, RL, ND, NDD, MU_EARTH), 1.0, order)
    Phi = kalman.transition_matrix(Fd, 1.0, "taylor", order)
    assert rel(km.dense_transition(T, n), Phi) < 1e-13
    rng = np.random.default_rng(1)
    A = rng.normal(size=(B, n, n))
    P = A @ np.swapaxes(A, -1, -2) + n * np.eye(n)
    Q = np.abs(rng.normal(size=(B, n)))
    got = km.predict_covariance_batch(P, T, Q)
    assert rel(got, kalman.predict_covariance(P, Phi, Q)) < 1e-13
    assert np.array_equal(got, np.swapaxes(got, -1, -2))


def test_dense_adds_each_rows_values_at_their_columns():
    """``model.dense``: every row's values added at their columns (the padding's zeros and any repeated column
    summed, in the order of the row's entries), as ``np.add.at`` does; the row-sparse input is not written."""
    rng = np.random.default_rng(6)
    B, m, k, n = 3, 7, 16, 12
    Hval = rng.standard_normal((B, m, k))
    cols = rng.integers(0, n, size=(m, k))
    cols[:, -3:] = 0  # padding on column 0, with values
    Hval[:, 2, -3:] = 0.0
    ref = np.zeros((B, m, n))
    np.add.at(ref, (slice(None), np.repeat(np.arange(m), k), cols.ravel()), Hval.reshape(B, -1))
    before = Hval.copy()
    np.testing.assert_array_equal(km.dense(Hval, cols, n), ref)
    np.testing.assert_array_equal(Hval, before)


@pytest.mark.parametrize("disparity,pseudo,focal", [(False, True, 1.0), (True, True, 800.0), (False, False, 1.0)])
def test_measurement_matches_numpy(disparity, pseudo, focal):
    x = states(N=6)
    B, n = x.shape
    vis = np.array([0, 2, 3, 5])
    alpha = 1e-5 * np.random.default_rng(2).normal(size=(B, 3))
    hx, Hval = km.measure_batch(x, km.StepModel(vis, 0.7, disparity, focal, pseudo, ND, NDD), alpha, True)
    C = 9 if disparity else 8
    h_np = [camera.h_features(x, 0.7, disparity, focal)[:, vis].reshape(B, -1)]
    H_np = [jacobians.H_features(x, 0.7, disparity, focal)[:, vis].reshape(B, -1, n)]
    if pseudo:
        h_np.append(inertia.h_pseudo(x, alpha, ND, NDD))
        H_np.append(jacobians.H_pseudo(x, alpha, ND, NDD))
    h_np, H_np = np.concatenate(h_np, -1), np.concatenate(H_np, -2)
    assert np.max(np.abs(hx - h_np) / np.maximum(np.abs(h_np), 1e-300)) < 1e-12
    H = km.dense(Hval, km.measurement_columns(n, vis, C, pseudo), n)
    assert rel(H, H_np) < 1e-12
    h_only, _ = km.measure_batch(x, km.StepModel(vis, 0.7, disparity, focal, pseudo, ND, NDD), alpha, False)
    assert np.array_equal(h_only, hx)


def test_measurement_jacobian_finite_differences():
    x = states(B=1, N=4)
    n = x.shape[-1]
    vis = np.arange(4)
    alpha = np.array([[1e-5, -2e-5, 3e-6]])

    def h(v):
        return km.measure_batch(v[None], km.StepModel(vis, 0.5, True, 1.0, True, ND, NDD), alpha, False)[0][0]

    _, Hval = km.measure_batch(x, km.StepModel(vis, 0.5, True, 1.0, True, ND, NDD), alpha, True)
    H = km.dense(Hval, km.measurement_columns(n, vis, 9, True), n)[0]
    fd = np.empty_like(H)
    for j in range(n):
        e = 1e-6 * max(abs(x[0, j]), 1e-2)
        d = np.zeros(n)
        d[j] = e
        fd[:, j] = (h(x[0] + d) - h(x[0] - d)) / (2 * e)
    scale = np.max(np.abs(H), axis=1, keepdims=True)
    assert np.all(np.abs(H - fd) <= 1e-6 * scale)


@pytest.mark.parametrize("n", [1, 2, 3, 8, 9, 10, 17, 70, 134])
def test_cholesky_on_the_transposed_layout(n):
    """``_cholesky_t`` (``_upper_blocked``'s blocks of 8 rows and pairs around BLAS products, on the transposed
    copy: 1, 2, 3, 8, 9, 10 and 17 rows are one row, a pair, a pair and a row, a block, a block and a row, a block
    and a pair, two blocks and a row) equals numpy's factor of ``A`` (LAPACK's), or with ``rev`` of ``J A J``,
    reading only the lower triangle of ``A``; False on a matrix that is not positive definite (its first, middle or
    last pivot) or has a non-finite pivot."""
    from stereopose_mc.core.kernels import cholesky as kchol

    rng = np.random.default_rng(300 + n)
    M = rng.standard_normal((n, n))
    A = M @ M.T + n * np.eye(n)
    Alow = np.tril(A) + np.triu(np.full((n, n), np.nan), 1)  # the upper triangle must not be read
    for rev, ref in ((False, np.linalg.cholesky(A)), (True, np.linalg.cholesky(A[::-1, ::-1]))):
        L = np.full((n, n), np.nan)
        assert kchol._cholesky_t(Alow, L, rev)
        np.testing.assert_allclose(L, ref, rtol=0, atol=1e-13 * np.abs(ref).max())
        assert np.all(np.triu(L, 1) == 0.0)
    bad = Alow.copy()
    bad[n - 1, n - 1] = -1.0
    assert not kchol._cholesky_t(bad, L, False)
    bad[n - 1, n - 1] = np.nan
    assert not kchol._cholesky_t(bad, L, False)
    for k, v in ((0, np.inf), (0, 0.0), (n // 2, -1.0), (n // 2, np.nan)):
        bad = Alow.copy()
        bad[k, k] = v
        assert not kchol._cholesky_t(bad, L, False), (k, v)
    # a singular matrix (rank n - 1 from its middle row on): its pivot there is round-off, not > 0 or not PD after
    if n >= 3:
        S = A.copy()
        m = n // 2
        S[m, :] = S[m - 1, :]
        S[:, m] = S[:, m - 1]
        assert not kchol._cholesky_t(S - 1e-9 * np.abs(A).max() * np.eye(n), L, False)
    # _cholesky_tu: the same factor in place from the upper triangle (the lower one not read)
    from stereopose_mc.core.kernels import cholesky as kc

    Lu = np.triu(A) + np.tril(np.full((n, n), np.nan), -1)
    assert kc._cholesky_tu(Lu)
    np.testing.assert_allclose(Lu, np.linalg.cholesky(A), rtol=0, atol=1e-13 * np.abs(A).max() ** 0.5)
    assert np.all(np.triu(Lu, 1) == 0.0)
    bad = np.triu(A)
    bad[n - 1, n - 1] = -1.0
    assert not kc._cholesky_tu(bad)
    # _upper_blocked's own layouts: the first n rows of a taller scratch (the update's Laug[:n]: blocks), a block of a
    # wider matrix and a Fortran-ordered copy (potrf's path): the same upper factor
    U_ref = np.linalg.cholesky(A).T
    tall = np.full((n + 3, n), np.nan)
    tall[:n] = np.triu(A) + np.tril(np.full((n, n), np.nan), -1)
    wide = np.zeros((n + 2, n + 2))
    wide[:n, :n] = np.triu(A)
    for U in (tall[:n], wide[:n, :n], np.asfortranarray(np.triu(A))):
        assert kc._upper_blocked(U)
        np.testing.assert_allclose(np.triu(U), U_ref, rtol=0, atol=1e-13 * np.abs(A).max() ** 0.5)
    assert np.all(np.isnan(tall[n:]))  # nothing written past the n rows


@pytest.mark.parametrize("n", [1, 5, 8, 9, 17, 29, 30, 32, 33, 64, 65, 70, 134])
def test_reverse_factor_solve_and_posterior_covariance(n):
    """``_factor(A, LA)`` is the Cholesky factor of ``A`` in reverse order (``A = U U^T``, ``U = J LA J`` upper
    triangular; up to 64 columns copied and factorized in place, past it on the transposed layout), reading only
    ``A``'s lower triangle; ``_solve`` with it equals numpy's solve; ``_posterior_covariance_rev`` (``L U^-T``, lower
    triangular, times its transpose; blocked by 8 rows up to 32 columns, by 16 past them) equals ``L A^-1 L^T`` by numpy, is exactly symmetric,
    and leaves in ``W`` the square root ``J M^T`` of it, ``M`` its Cholesky factor; False on a matrix that is not
    positive definite."""
    from stereopose_mc.core.kernels import triangular as ktri

    rng = np.random.default_rng(200 + n)
    A1, A2 = rng.standard_normal((2, n, n))
    P, A = A1 @ A1.T + n * np.eye(n), A2 @ A2.T + np.eye(n)
    Alow = np.tril(A) + np.triu(np.full((n, n), np.nan), 1)  # the upper triangle must not be read
    L = np.linalg.cholesky(P)
    LA = np.full((n, n), np.nan)
    assert ktri._factor(Alow, LA)
    U = LA[::-1, ::-1]
    assert np.all(np.tril(U, -1) == 0.0)
    np.testing.assert_allclose(U @ U.T, A, rtol=0, atol=1e-12 * np.abs(A).max())
    b = rng.standard_normal(n)
    x = b.copy()
    ktri._solve(LA, x)
    np.testing.assert_allclose(A @ x, b, rtol=0, atol=1e-10 * np.abs(b).max())
    out, W = np.full((n, n), np.nan), np.full((n, n), np.nan)
    ktri._posterior_covariance_rev(L, LA, out, W)
    ref = L @ np.linalg.solve(A, L.T)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    assert np.array_equal(out, out.T)
    Mt = W[::-1]  # M^T: upper triangular, positive diagonal, the Cholesky factor of out
    assert np.all(np.tril(Mt, -1) == 0.0) and np.all(np.diag(Mt) > 0.0)
    np.testing.assert_allclose(Mt.T, np.linalg.cholesky(ref), rtol=0, atol=1e-11 * np.abs(Mt).max())
    bad = A.copy()
    bad[0, 0] = -1.0
    assert not ktri._factor(bad, LA)


def _centering(N, n):
    """The aligned chart's centered coordinates as a dense matrix ``T (n x n)``: common block, the points' mean,
    the first ``N - 1`` points' deviations from it, ``k``."""
    T = np.eye(n)
    p0 = 12
    T[p0 : p0 + 3 * N, p0 : p0 + 3 * N] = 0.0
    mean = np.kron(np.ones((1, N)) / N, np.eye(3))
    T[p0 : p0 + 3, p0 : p0 + 3 * N] = mean
    for f in range(N - 1):
        T[p0 + 3 + 3 * f : p0 + 6 + 3 * f, p0 : p0 + 3 * N] = -mean
        T[p0 + 3 + 3 * f : p0 + 6 + 3 * f, p0 + 3 * f : p0 + 3 * f + 3] += np.eye(3)
    return T


@pytest.mark.parametrize("N", [1, 2, 7, 40])
def test_centered_coordinates_of_the_aligned_chart(N):
    """``_center_cov`` is ``T P T^T`` (lower triangle; with a common point error 1e4 times the deviations, the
    deviations' block stays within 2 ulps of P's largest entry, against an extended-precision reference; nothing
    written past its rows, also with one point, where ``T`` is the identity),
    ``_uncenter_cov`` its inverse (exactly symmetric), ``_uncenter_vec_to`` is ``T^-1 v``; ``_centered_model_rows``
    gives ``H' = H_e T^-1`` with the last point's deviations through the virtual columns
    (``_centered_virtual_rows``: the sum of the other deviations' rows)."""
    from stereopose_mc.core.kernels import centred as kcen

    rng = np.random.default_rng(N)
    n = 12 + 3 * N + 2
    T = _centering(N, n)
    Ti = np.linalg.inv(T)
    X = rng.standard_normal((n, n))
    Pd = X @ X.T / n + np.eye(n)  # the deviations ~1
    G = np.zeros((n, n))
    G[12 : 12 + 3 * N, 12 : 12 + 3 * N] = 1e8 * np.kron(np.ones((N, N)), np.eye(3))  # a common error of 1e4
    P = Pd + G
    buf = np.full((n + 3, n), -7.0)  # Pc with 3 sentinel rows after it
    Pc, tmp = buf[:n], np.empty((n, n))
    kcen._center_cov(P, Pc, tmp, N)
    assert np.all(buf[n:] == -7.0)
    Tl = T.astype(np.longdouble)  # the reference in extended precision from P as stored (its 1e8 + ~1 entries)
    ref = (Tl @ P.astype(np.longdouble) @ Tl.T).astype(float)
    il = np.tril_indices(n)
    dev = slice(15, 12 + 3 * N)
    # the deviations' block to within 2 ulps of P's largest entry: the rounding of the mean itself (compensated
    # sums, not N ulps)
    np.testing.assert_allclose(Pc[dev, dev], ref[dev, dev], rtol=0, atol=2 * np.finfo(float).eps * np.abs(P).max())
    np.testing.assert_allclose(Pc[il], ref[il], rtol=0, atol=1e-12 * np.abs(ref).max())
    back = np.full((n, n), np.nan)
    Pcs = np.tril(Pc) + np.tril(Pc, -1).T
    kcen._uncenter_cov(Pcs, back, tmp, N)
    np.testing.assert_allclose(back, Ti @ Pcs @ Ti.T, rtol=0, atol=1e-12 * np.abs(P).max())
    assert np.array_equal(back, back.T)
    v = rng.standard_normal(n)
    out = np.empty(n)
    kcen._uncenter_vec_to(T @ v, out, N)
    np.testing.assert_allclose(out, v, rtol=0, atol=1e-13)
    # H' = H_e T^-1 on aligned-chart rows (9 common columns, own point, 3 virtual = every point's sum)
    _, cols, Hval = _staircase_rows(rng, N, True, ())
    m = cols.shape[0]
    Hc, cc = np.zeros_like(Hval), np.zeros_like(cols)
    kcen._centered_model_rows(Hval, cols, Hc, cc, n, N)
    He = np.zeros((m, n))
    Hp = np.zeros((m, n))
    S = np.zeros((3, n))  # the virtual columns of H': the sum of the deviations d_0 .. d_{N-2}
    for f in range(N - 1):
        S[:, 15 + 3 * f : 18 + 3 * f] = np.eye(3)
    for r in range(m):
        for h, c in zip(Hval[r], cols[r]):
            if c >= n:
                He[r, 12 + (c - n) : 12 + 3 * N : 3] += h
            else:
                He[r, c] += h
        for h, c in zip(Hc[r], cc[r]):
            if c >= n:
                Hp[r] += h * S[c - n]
            else:
                Hp[r, c] += h
    np.testing.assert_allclose(Hp, He @ Ti, rtol=0, atol=1e-12 * np.abs(He).max())
    Laug = np.vstack([rng.standard_normal((n, n)), np.zeros((3, n))])
    kcen._centered_virtual_rows(Laug, N)
    np.testing.assert_allclose(Laug[n:], S @ Laug[:n], rtol=1e-13, atol=1e-13)


def _staircase_rows(rng, N, virtual, masked):
    """Row-sparse model rows like the kernels' (``NNZ`` wide): per feature 8 rows on its own point's 3 columns and
    the 12 common ones, or (``virtual``, the aligned chart) the first 9 and the 3 virtual columns ``n .. n+2``; 3
    pseudo rows on
    ``omega, delta, k``; rows in a shuffled order, a masked feature's rows all zero."""
    from stereopose_mc.core.kernels.model import NNZ

    n = 12 + 3 * N + 2
    rows_c, rows_v = [], []
    for f in range(N):
        own = [12 + 3 * f + a for a in range(3)]
        c = (list(range(9)) + own + [n, n + 1, n + 2]) if virtual else (list(range(12)) + own)
        for _ in range(8):
            rows_c.append(c)
            rows_v.append(rng.standard_normal(len(c)) * (0.0 if f in masked else 1.0))
    for _ in range(3):
        c = [6, 7, 8, 9, 10, 11, n - 2, n - 1]
        rows_c.append(c)
        rows_v.append(rng.standard_normal(len(c)))
    m = len(rows_c)
    cols, Hval = np.zeros((m, NNZ), np.int64), np.zeros((m, NNZ))
    order = rng.permutation(m)
    for r, i in enumerate(order):
        cols[r, : len(rows_c[i])], Hval[r, : len(rows_v[i])] = rows_c[i], rows_v[i]
    return n, cols, Hval


def _whitening_inputs(rng, n, m, virtual):
    """A Cholesky factor ``L`` of a random SPD matrix (with 3 random rows appended for the virtual columns), ``y``,
    ``h`` and ``R^-1/2`` for ``m`` rows: the inputs of the whitening kernels."""
    X = rng.standard_normal((n, n))
    L = np.linalg.cholesky(X @ X.T + n * np.eye(n))
    Laug = np.vstack([L, rng.standard_normal((3, n))]) if virtual else L
    y, hx = rng.standard_normal((2, m))
    return Laug, y, hx, 1.0 / rng.uniform(0.5, 2.0, m)


def _dense_whitened(cols, Hval, rws, Laug):
    """The dense ``Hw = R^-1/2 H L_aug`` of the row-sparse ``H`` (numpy)."""
    Hd = np.zeros((cols.shape[0], Laug.shape[0]))
    for r in range(cols.shape[0]):
        np.add.at(Hd[r], cols[r], Hval[r])
    return (rws[:, None] * Hd) @ Laug


@pytest.mark.parametrize("N,virtual,masked", [(7, True, ()), (7, False, ()), (20, True, (3,)), (40, True, (0, 39)),
                                              (40, False, (5,))])  # fmt: skip
def test_whiten_information_equals_the_dense_product(N, virtual, masked):
    """``_whiten_information`` (``A = I + L^T Y L`` from the arrow-shaped information ``Y = H^T R^-1 H``, ``L^T W``
    by strips, the virtual columns as dense rows of ``L_aug``) gives the ``A = I + Hw^T Hw`` and ``g = Hw^T rw``
    of the dense product ``Hw = R^-1/2 H L_aug``, and ``_whiten_g`` takes it past 64 columns."""
    from stereopose_mc.core.kernels import whiten as kw

    rng = np.random.default_rng(N + 7 * len(masked))
    n, cols, Hval = _staircase_rows(rng, N, virtual, masked)
    m = cols.shape[0]
    Laug, y, hx, rws = _whitening_inputs(rng, n, m, virtual)
    Hw = _dense_whitened(cols, Hval, rws, Laug)
    rw_ref = rws * (y - hx)
    A_ref, g_ref = np.eye(n) + Hw.T @ Hw, Hw.T @ rw_ref
    rw, A, g = np.empty(m), np.full((n, n), np.nan), np.empty(n)
    n_ws, n_wi = kw.scratch_sizes(n, Laug.shape[0] - n)
    ws, wi = np.full(n_ws, np.nan), np.empty(n_wi, np.int64)
    kw._whiten_information(hx, Hval, cols, y, rws, Laug, rw, A, g, ws, wi, True)
    np.testing.assert_allclose(rw, rw_ref, rtol=1e-15, atol=0)
    np.testing.assert_allclose(A, A_ref, rtol=0, atol=1e-13 * np.abs(A_ref).max())
    np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-13 * np.abs(g_ref).max())
    assert np.array_equal(A, A.T)
    # without ``upper`` (an EKF step, which reads only the lower triangle): the same lower triangle and g, and the
    # upper triangle not mirrored (left NaN above the diagonal blocks of the strips)
    A1, g1 = np.full((n, n), np.nan), np.empty(n)
    kw._whiten_information(hx, Hval, cols, y, rws, Laug, rw, A1, g1, ws, wi, False)
    low = np.tril_indices(n)
    assert np.array_equal(A1[low], A[low]) and np.array_equal(g1, g)
    assert np.isnan(A1[0, n - 1])
    A2, g2 = np.empty((n, n)), np.empty(n)
    kw._whiten_g(hx, Hval, cols, y, rws, Laug, np.empty((m, n)), rw, A2, g2, ws, wi, True)
    if n > kw.LARGE_N:
        assert np.array_equal(A2, A) and np.array_equal(g2, g)
    else:  # the dense product below LARGE_N (g summed row by row as the rows are formed)
        np.testing.assert_allclose(A2, A_ref, rtol=0, atol=1e-13 * np.abs(A_ref).max())
        np.testing.assert_allclose(g2, g_ref, rtol=0, atol=1e-13 * np.abs(g_ref).max())


def test_information_rows_are_the_sparse_gram_product():
    """``_information_rows``: ``Y = H^T R^-1 H`` and ``H^T R^-1 (y - h)`` of the row-sparse rows (a masked feature's
    zero rows add nothing), against the dense products; ``Y`` has the arrow shape: two points never meet."""
    from stereopose_mc.core.kernels import whiten as kw
    from stereopose_mc.core.kernels.model import NNZ

    rng = np.random.default_rng(5)
    n, cols, Hval = _staircase_rows(rng, 6, False, masked=(2,))
    m = cols.shape[0]
    _, y, hx, rws = _whitening_inputs(rng, n, m, False)
    Hd = np.zeros((m, n))
    for r in range(m):
        np.add.at(Hd[r], cols[r], Hval[r])
    Hd *= rws[:, None]
    rw, Y, gy = np.empty(m), np.full((n, n), np.nan), np.empty(n)
    kw._information_rows(hx, Hval, cols, y, rws, rw, Y, gy, np.empty(NNZ), np.empty(NNZ, np.int64))
    np.testing.assert_allclose(Y, Hd.T @ Hd, rtol=0, atol=1e-13 * np.abs(Y).max())
    np.testing.assert_allclose(gy, Hd.T @ rw, rtol=0, atol=1e-13 * np.abs(gy).max())
    assert np.all(Y[12:15, 15:18] == 0.0) and np.all(Y[18:21, 12:15] == 0.0)  # points 0 and 2 (masked), 1
    assert np.all(Y[18:21] == 0.0)  # the masked point's rows


@pytest.mark.parametrize("virtual", [False, True])
def test_whiten_forms_rows_with_the_same_columns_in_pairs(virtual):
    """``_whiten`` forms two consecutive rows that see the same columns in one pass: each row equals, bit for bit,
    the row whitened alone, also where one row of a pair has a group of four zero values (which a row alone skips)
    or a whole masked feature; ``Hw``, ``A`` and ``g`` equal the dense product's to round-off."""
    from stereopose_mc.core.kernels import whiten as kw

    rng = np.random.default_rng(23 + virtual)
    n, cols, Hval = _staircase_rows(rng, 5, virtual, masked=(2,))
    order = np.lexsort(cols.T[::-1])  # a feature's rows next to each other, as the model gives them
    cols, Hval = np.ascontiguousarray(cols[order]), np.ascontiguousarray(Hval[order])
    Hval[3, 4:8] = 0.0  # a zero group in one row of a pair
    Hval[10, 0:4] = 0.0
    m = cols.shape[0]
    Laug, y, hx, rws = _whitening_inputs(rng, n, m, virtual)
    Hw, rw, A, g = np.empty((m, n)), np.empty(m), np.empty((n, n)), np.empty(n)
    kw._whiten(hx, Hval, cols, y, rws, Laug, Hw, rw, A, g)
    pairs = sum(np.array_equal(cols[r], cols[r + 1]) for r in range(m - 1))
    assert pairs > m // 2  # the paired path is exercised
    for r in range(m):  # each row alone
        H1, rw1, A1, g1 = np.empty((1, n)), np.empty(1), np.empty((n, n)), np.empty(n)
        kw._whiten(hx[r : r + 1], Hval[r : r + 1], cols[r : r + 1], y[r : r + 1], rws[r : r + 1], Laug, H1, rw1, A1, g1)
        assert np.array_equal(H1[0], Hw[r]), r
    Hw_ref = _dense_whitened(cols, Hval, rws, Laug)
    np.testing.assert_allclose(Hw, Hw_ref, rtol=0, atol=1e-13 * np.abs(Hw_ref).max())
    np.testing.assert_allclose(A, np.eye(n) + Hw_ref.T @ Hw_ref, rtol=0, atol=1e-13 * np.abs(A).max())
    np.testing.assert_allclose(g, Hw_ref.T @ (rws * (y - hx)), rtol=0, atol=1e-13 * np.abs(g).max())
    assert np.array_equal(A, A.T)


@pytest.mark.parametrize("n", [1, 2, 7, 30, 32, 33, 70, 100])
def test_gram_lower_blocked(n):
    """The lower triangle of ``M^T M`` (blocked past 32 columns) equals numpy's product."""
    from stereopose_mc.core.kernels import whiten as kw

    M = np.random.default_rng(n).standard_normal((2 * n + 3, n))
    G = np.full((n, n), np.nan)
    kw._gram_lower(M, G)
    ref = M.T @ M
    il = np.tril_indices(n)
    np.testing.assert_allclose(G[il], ref[il], rtol=0, atol=1e-12 * np.abs(ref).max())


@pytest.mark.parametrize("n", [1, 3, 15, 29, 70])
def test_cholesky_potrf_in_place_and_on_blocks(n):
    """``update._cholesky`` (LAPACK potrf called in place) equals numpy's factor, also on a block ``C[:n, :n]`` of a
    larger array (leading dimension = row stride) and on a non-unit-stride view; False, not a crash, on a matrix that
    is not positive definite or has a non-finite pivot."""
    from numba import njit

    from stereopose_mc.core.kernels import cholesky as kchol

    @njit
    def on_block(C, W, m):
        return kchol._cholesky(C[:m, :m], W[:m, :m])

    rng = np.random.default_rng(n)
    M = rng.standard_normal((n, n))
    A = M @ M.T + n * np.eye(n)
    ref = np.linalg.cholesky(A)
    L = np.full((n, n), np.nan)
    assert kchol._cholesky(A, L)
    np.testing.assert_allclose(L, ref, rtol=0, atol=1e-13 * np.abs(ref).max())
    assert np.all(np.triu(L, 1) == 0.0)
    C = np.full((n + 4, n + 4), 7.0)
    C[:n, :n] = A
    W = np.full((n + 4, n + 4), 5.0)
    assert on_block(C, W, n)
    np.testing.assert_allclose(W[:n, :n], ref, rtol=0, atol=1e-13 * np.abs(ref).max())
    assert np.all(W[n:] == 5.0) and np.all(W[:, n:] == 5.0)  # nothing written outside the block
    Ls = np.full((n, 2 * n), np.nan)
    assert kchol._cholesky(A, Ls[:, ::2])  # strided columns: through a contiguous copy
    np.testing.assert_allclose(Ls[:, ::2], ref, rtol=0, atol=1e-13 * np.abs(ref).max())
    bad = A.copy()
    bad[n - 1, n - 1] = -1.0
    assert not kchol._cholesky(bad, L)
    bad[n - 1, n - 1] = np.inf
    assert not kchol._cholesky(bad, L)
    bad[n - 1, n - 1] = np.nan
    assert not kchol._cholesky(bad, L)


@pytest.mark.parametrize("n", [0, 1, 3, 4, 7, 16, 29, 134])
def test_dot_and_chol_solve(n):
    """The four-sum ``_dot``/``_dot_row`` equal ``np.dot``; ``_forward`` and ``_chol_solve`` (rows of ``L`` for the
    back substitution) equal numpy's triangular and full solves."""
    from stereopose_mc.core.kernels import cholesky as kchol
    from stereopose_mc.core.kernels import rows as kr

    rng = np.random.default_rng(100 + n)
    a, b = rng.standard_normal((2, n))
    ref = float(np.dot(a, b)) if n else 0.0
    assert kr._dot(a, b, 0, n) == pytest.approx(ref, rel=1e-13, abs=1e-13)
    M = np.vstack([b, a]) if n else np.zeros((2, 0))
    assert kr._dot_row(M, 1, b, 0, n) == pytest.approx(ref, rel=1e-13, abs=1e-13)
    if n == 0:
        return
    assert kr._dot(a, b, 1, n - 1) == pytest.approx(float(np.dot(a[1 : n - 1], b[1 : n - 1])), rel=1e-13, abs=1e-13)
    X = rng.standard_normal((n, n))
    L = np.linalg.cholesky(X @ X.T + n * np.eye(n))
    w = np.empty(n)
    kchol._forward(L, a, w)
    np.testing.assert_allclose(L @ w, a, rtol=0, atol=1e-12 * max(1.0, np.abs(a).max()))
    x = a.copy()
    kchol._chol_solve(L, x)
    np.testing.assert_allclose(x, np.linalg.solve(L @ L.T, a), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("n", [0, 1, 3, 4, 7, 16, 29])
def test_row_kernels_read_rows_in_place(n):
    """``_dot_rows`` is ``_dot_row`` of a row taken in place (bit for bit, and ``np.dot`` to round-off);
    ``_combine_rows`` is ``O[o, lo:hi] += sign Cf[c, k0:k1] M[k0:k1, lo:hi]`` (also with a transposed ``Cf``, as
    ``_cholesky_small`` calls it); ``_ptr`` addresses element ``i * ld + j`` of a matrix."""
    from numba import njit

    from stereopose_mc.core.kernels import rows as kr

    rng = np.random.default_rng(300 + n)
    M, V = rng.standard_normal((2, 5, n))
    for i, j in ((0, 0), (1, 3), (4, 2)):
        got = kr._dot_rows(M, i, V, j, 0, n)
        assert got == kr._dot_row(M, i, V[j].copy(), 0, n)
        assert got == pytest.approx(float(np.dot(M[i], V[j])) if n else 0.0, rel=1e-13, abs=1e-13)
        if n > 2:
            assert kr._dot_rows(M, i, V, j, 1, n - 1) == kr._dot_row(M, i, V[j].copy(), 1, n - 1)
    if n == 0:
        return
    K = 9
    A, Cf = rng.standard_normal((K, n)), rng.standard_normal((4, K))
    Cf[1, 4:8] = 0.0  # a group of four zero coefficients (skipped)
    for o, c, lo, hi, k0, k1, sign in ((0, 1, 0, n, 0, K, -1.0), (2, 3, n // 2, n, 2, 7, 1.0), (1, 0, 0, 1, 0, 0, 1.0)):
        O = rng.standard_normal((3, n))
        want = O.copy()
        want[o, lo:hi] += sign * (Cf[c, k0:k1] @ A[k0:k1, lo:hi])
        O1, O2 = O.copy(), O.copy()
        kr._combine_rows(O1, o, lo, hi, A, Cf, c, k0, k1, sign)
        np.testing.assert_allclose(O1, want, rtol=1e-13, atol=1e-13)
        kr._combine_rows(O2, o, lo, hi, A, np.ascontiguousarray(Cf.T).T, c, k0, k1, sign)  # a strided Cf
        np.testing.assert_array_equal(O2, O1)

    @njit
    def read(a, k):
        return kr._ptr(a, k)[0]

    B = rng.standard_normal((4, n))
    for i, j in ((0, 0), (3, n - 1), (2, n // 2)):
        assert read(B, i * n + j) == B[i, j]


@settings(max_examples=60, deadline=None)
@given(n=st_h.integers(0, 140), cuts=st_h.lists(st_h.integers(0, 150), min_size=3, max_size=3),
       seed=st_h.integers(0, 2**32 - 1))
def test_dot_row_pair_is_two_dot_rows_bit_for_bit(n, cuts, seed):
    """``_dot_row_pair`` is ``_dot_row`` of rows ``i`` and ``i + 1`` (bit for bit: the same chains, the same tails),
    for any ``lo <= hi_i <= hi_j``; the update's ``A v`` (``update._row_products``) and ``centred._lower_mul``'s
    ``L z``, which take rows by pairs, equal the row-by-row ``_dot_row`` bit for bit (odd sizes: a last row alone)."""
    from stereopose_mc.core.kernels import centred as kc, rows as kr, update as ku

    rng = np.random.default_rng(seed)
    lo, hi_i, hi_j = sorted(cuts)
    w = hi_j + 1
    M, b = rng.standard_normal((3, w)) * 10.0 ** rng.integers(-3, 4, (3, w)), rng.standard_normal(w)
    got = kr._dot_row_pair(M, 1, b, lo, hi_i, hi_j)
    assert got == (kr._dot_row(M, 1, b, lo, hi_i), kr._dot_row(M, 2, b, lo, hi_j))
    A, v = rng.standard_normal((n, n)), rng.standard_normal(n)
    out, low = np.empty(n), np.empty(n)
    ku._row_products(A, v, out)
    kc._lower_mul(np.tril(A), v, low)
    assert out.tolist() == [kr._dot_row(A, i, v, 0, n) for i in range(n)]
    assert low.tolist() == [kr._dot_row(np.tril(A), i, v, 0, i + 1) for i in range(n)]
    np.testing.assert_allclose(out, A @ v, rtol=1e-12, atol=1e-12 * max(1.0, np.abs(A).sum()))


@pytest.mark.parametrize("n", [1, 5, 29, 70])
def test_sparse_rows_product_equals_the_dense_product(n):
    """``rows._sparse_rows_product`` from ``_row_nonzeros`` is ``Y M`` (to round-off) for rows with 0 to ``n``
    non-zeros, and its ``lower`` form is the lower triangle of that product."""
    from stereopose_mc.core.kernels import rows as kr

    rng = np.random.default_rng(700 + n)
    Y, M = rng.standard_normal((2, n, n))
    Y[rng.random((n, n)) < 0.7] = 0.0  # rows of every density: one empty, one dense
    Y[0] = 0.0
    Y[-1] = rng.standard_normal(n)
    nz, cnt = np.empty((n, n), np.int64), np.empty(n, np.int64)
    kr._row_nonzeros(Y, nz, cnt)
    assert cnt.tolist() == np.count_nonzero(Y, axis=1).tolist()
    O = np.full((n, n), np.nan)
    kr._sparse_rows_product(Y, nz, cnt, M, O, False)
    np.testing.assert_allclose(O, Y @ M, rtol=1e-13, atol=1e-13 * np.abs(M).max() * n)
    L = np.full((n, n), 7.0)
    kr._sparse_rows_product(Y, nz, cnt, M, L, True)
    assert np.array_equal(np.tril(L), np.tril(O)) and np.array_equal(np.triu(L, 1), np.triu(np.full((n, n), 7.0), 1))


def test_cached_kernels_load_and_run_in_a_new_process(tmp_path):
    """Numba's on-disk cache: the kernels compiled here (and saved) load and run in a fresh process. (A recursive
    call between two specializations compiled fine but its cached copy did not link: a segfault on reload.)"""
    import os
    import subprocess
    import sys

    script = tmp_path / "reload.py"
    script.write_text(
        "import numpy as np\n"
        "from stereopose_mc.core.kernels import cholesky as kchol, consistency as kc\n"
        "rng = np.random.default_rng(0)\n"
        "n = 29; M = rng.standard_normal((n, n)); A = M @ M.T + n * np.eye(n); L = np.empty((n, n))\n"
        "assert kchol._cholesky(A, L)\n"
        "x = np.zeros((2, 30)); x[:, 9] = 1.0; x[:, 13:28] = rng.standard_normal((2, 15)); xt = x.copy()\n"
        "xt[:, 0] += 0.1\n"
        "out, pd = kc.nees_batch(x, np.broadcast_to(np.eye(29) * 0.01, (2, 29, 29)).copy(), xt, False,\n"
        "                        np.empty((0, 29, 29)))\n"
        "assert pd.all() and np.isfinite(out).all(), out\n"
        "print('ok', round(float(out[0, 0]), 6))\n"
    )
    x = np.zeros((2, 30))
    x[:, 9] = 1.0
    x[:, 13:28] = np.random.default_rng(0).standard_normal((2, 15))
    from stereopose_mc.core.kernels import consistency as kc

    kc.nees_batch(x, np.broadcast_to(np.eye(29) * 0.01, (2, 29, 29)).copy(), x.copy(), False,
                  np.empty((0, 29, 29)))  # compiled, cached here
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    for _ in range(2):  # the first may still compile (another specialization); the second loads from the cache
        r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=600)
        assert r.returncode == 0, (r.returncode, r.stderr[-2000:])
        assert r.stdout.startswith("ok ")
    assert float(r.stdout.split()[1]) == pytest.approx(0.1**2 / 0.01, rel=1e-9)


def test_kernel_cache_is_stamped_by_the_whole_package(tmp_path):
    """Every kernel's Numba cache is keyed by the sources of all ``core/kernels`` modules (``_cache``), so editing a
    callee's module (``update._cholesky``) invalidates its callers' cached code in other modules; functions outside
    the package keep Numba's own locators."""
    from numba import njit

    from stereopose_mc.core.kernels import _cache, consistency as kc, update as ku

    assert _cache.install()  # installed by the package already: idempotent
    assert sum(c in _cache.LOCATORS for c in _cache._IMPL._locator_classes) == len(_cache.LOCATORS)
    for kernel in (ku.iekf_update_batch, kc.nees_batch, km.predict_state_batch):
        loc = kernel._cache._impl.locator
        assert isinstance(loc, _cache.LOCATORS), type(loc)
        assert loc.get_source_stamp() == _cache.package_stamp()

    @njit(cache=True)
    def outside(a):
        return a + 1

    assert not isinstance(outside._cache._impl.locator, _cache.LOCATORS)
    # the stamp covers every module's content, and only that
    for name in ("a.py", "b.py"):
        (tmp_path / name).write_text(f"x = '{name}'\n")
    s0 = _cache.package_stamp(tmp_path)
    assert _cache.package_stamp(tmp_path) == s0
    (tmp_path / "b.py").write_text("x = 'changed'\n")
    s1 = _cache.package_stamp(tmp_path)
    assert s1 != s0
    (tmp_path / "c.py").write_text("")
    assert _cache.package_stamp(tmp_path) not in (s0, s1)
    (tmp_path / "notes.txt").write_text("not a module")
    assert len(_cache.source_files(tmp_path)) == 3


def test_kernel_cache_stamp_covers_the_core_modules_the_kernels_import(tmp_path):
    """The kernels read the state layout's offsets from ``core/layout.py`` as compile-time constants: the cache stamp
    covers every ``core`` module a kernel module imports (``from ..layout import``, ``from .. import x``), so editing
    the layout, or a kernel starting to import another core module, recompiles the kernels."""
    from pathlib import Path

    from stereopose_mc.core import layout
    from stereopose_mc.core.kernels import _cache

    assert Path(layout.__file__).resolve() in _cache.core_dependencies()
    kernels = tmp_path / "core" / "kernels"
    kernels.mkdir(parents=True)
    (kernels / "a.py").write_text("from ..layout import QUAT\n")
    (tmp_path / "core" / "layout.py").write_text("QUAT = 9\n")
    (tmp_path / "core" / "other.py").write_text("X = 1\n")
    assert [p.name for p in _cache.core_dependencies(kernels)] == ["layout.py"]
    s0 = _cache.package_stamp(kernels)
    (tmp_path / "core" / "other.py").write_text("X = 2\n")  # not imported: the stamp stays
    assert _cache.package_stamp(kernels) == s0
    (tmp_path / "core" / "layout.py").write_text("QUAT = 12\n")  # the layout edited
    s1 = _cache.package_stamp(kernels)
    assert s1 != s0
    (kernels / "b.py").write_text("from .. import other\n")  # a kernel module imports another core module
    s2 = _cache.package_stamp(kernels)
    assert [p.name for p in _cache.core_dependencies(kernels)] == ["layout.py", "other.py"]
    (tmp_path / "core" / "other.py").write_text("X = 3\n")
    assert _cache.package_stamp(kernels) not in (s0, s1, s2)


def test_kernel_cache_finds_the_core_imports_as_a_whole_parse_does(tmp_path):
    """``_cache`` finds the ``from ..`` imports by their lines (one statement parsed at a time, not the modules):
    the same imports as ``ast.walk`` of each whole module, for the package and for the forms it must handle."""
    import ast

    from stereopose_mc.core.kernels import _cache

    def whole(src: bytes):
        return sorted((n.module or "", tuple(a.name for a in n.names)) for n in ast.walk(ast.parse(src))
                      if isinstance(n, ast.ImportFrom) and n.level == 2)  # fmt: skip

    def by_lines(src: bytes):
        return sorted((n.module or "", tuple(a.name for a in n.names)) for n in _cache._imports_from_parent(src))

    for p in _cache.source_files():
        assert by_lines(p.read_bytes()) == whole(p.read_bytes()), p.name
    forms = (b"from ..layout import (A,\n    B)  # two lines\nfrom .. import x, y\nfrom . import z\n"
             b"def f():\n    from ..other import C\n    from ...far import D\n")  # fmt: skip
    assert by_lines(forms) == whole(forms) == [("", ("x", "y")), ("layout", ("A", "B")), ("other", ("C",))]
    in_string = b'"""\nfrom .. import (\n"""\nfrom ..layout import Q\n'  # a candidate that does not parse alone
    assert by_lines(in_string) == whole(in_string) == [("layout", ("Q",))]
