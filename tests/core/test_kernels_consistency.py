"""The compiled NEES (core/kernels/consistency.py) equals its numpy twin core.aligned.nees_report."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st_h

pytest.importorskip("numba")

from stereopose_mc.core import aligned, quaternion as qt, state as st  # noqa: E402
from stereopose_mc.core.kernels import consistency as kc  # noqa: E402

RNG = np.random.default_rng(5)


def _case(B, N):
    q = qt.normalize(RNG.standard_normal((B, 4)))
    xt = st.assemble(RNG.standard_normal((B, 3)) + [0, 40, 0], 1e-2 * RNG.standard_normal((B, 3)),
                     1e-2 * RNG.standard_normal((B, 3)), q, RNG.standard_normal((B, N, 3)),
                     0.2 * RNG.standard_normal((B, 2)))  # fmt: skip
    ne = xt.shape[1] - 1
    A = RNG.standard_normal((B, ne, ne))
    P = A @ A.transpose(0, 2, 1) / ne * 1e-3 + 1e-5 * np.eye(ne)
    xh = aligned.chart(xt, 0.03 * RNG.standard_normal((B, ne)))
    return xh, P, xt


@pytest.mark.parametrize("N", [1, 3, 5, 8])
def test_compiled_nees_equals_the_numpy_report(N):
    xh, P, xt = _case(40, N)
    ref = aligned.nees_report(xh, P, xt)
    got = kc.nees_report(xh, P, xt)
    assert set(got) == set(ref)
    for k in kc.KEYS:
        np.testing.assert_allclose(got[k], ref[k], rtol=1e-10, err_msg=k)
    # one shared truth (the engine's usual case) broadcasts like the numpy report
    one = kc.nees_report(xh, P, xt[0])
    np.testing.assert_allclose(one["nees"], aligned.nees_report(xh, P, xt[0])["nees"], rtol=1e-10)


def test_broken_trials_give_nan_like_numpy():
    xh, P, xt = _case(4, 2)
    P[1, 0, 0] = -1.0  # not positive definite
    xh[2, 0] = np.nan  # a lost trial
    got, ref = kc.nees_report(xh, P, xt), aligned.nees_report(xh, P, xt)
    assert np.isnan(got["nees"][1]) and np.isnan(ref["nees"][1])
    assert all(np.isnan(got[k][2]) for k in kc.KEYS)
    np.testing.assert_allclose(got["nees"][[0, 3]], ref["nees"][[0, 3]], rtol=1e-10)


def test_gauge_nees_with_a_wide_gauge_direction():
    """The gauge-projected NEES from the full NEES's factor (projection of ``L^-1 e`` off ``L^-1 G``) against an
    exact value: ``P`` block-diagonal in an orthonormal basis ``[V, G]`` (``G`` the gauge, 10 m wide; ``V`` its
    complement, 1 cm to 1 m) and ``e = V a + G g``: the gauge-projected NEES is ``a^T C^-1 a`` whatever ``g``."""
    N = 5
    xh, _, xt = _case(20, N)
    ne = xh.shape[-1] - 1
    G = np.zeros((ne, 3))
    G[12 : 12 + 3 * N] = np.tile(np.eye(3), (N, 1)) / np.sqrt(N)
    V = aligned.gauge_complement(ne + 1)
    V = np.linalg.qr(V)[0]  # orthonormal, orthogonal to G
    for b in range(20):
        Cr = RNG.standard_normal((ne - 3, ne - 3)) * np.logspace(-2, 0, ne - 3)[:, None]  # 1 cm to 1 m
        C = Cr @ Cr.T / ne + 1e-6 * np.eye(ne - 3)
        P = V @ C @ V.T + 1e2 * G @ G.T
        a = np.linalg.cholesky(C) @ RNG.standard_normal(ne - 3)
        exact = a @ np.linalg.solve(C, a)
        e_target = V @ a + G @ (10.0 * RNG.standard_normal(3))
        # estimate whose aligned error is e_target: x_hat = x_true [-] e; use the chart at the truth instead
        xh_b = xt[b]
        xt_b = aligned.chart(xh_b[None], e_target[None])[0]
        got = kc.nees_report(xh_b[None], P[None], xt_b[None])["nees_gauge"][0]
        e = aligned.local(xh_b[None], xt_b[None])[0]
        np.testing.assert_allclose(e, e_target, rtol=1e-9, atol=1e-12)  # the chart's inverse (tested elsewhere)
        np.testing.assert_allclose(got, exact, rtol=1e-7)


def test_pd_flag_is_the_factorization_of_P():
    xh, P, xt = _case(3, 2)
    P[1] = -P[1]
    _, pd = kc.nees_and_pd(xh, P, xt)
    assert pd.tolist() == [True, False, True]


def test_full_state_covariance_is_mapped_like_the_numpy_path():
    """A full-state filter's ``P (n x n)`` enters as ``T P T^T`` (``mc.trial.aligned_covariance``): same NEES."""
    from stereopose_mc.mc import trial

    xh, _, xt = _case(25, 4)
    n = xh.shape[-1]
    A = RNG.standard_normal((25, n, n))
    P = A @ A.transpose(0, 2, 1) / n * 1e-3 + 1e-6 * np.eye(n)
    ref = trial.nees_of(xh, P, xt, "full", "numpy")
    got, pd = kc.nees_and_pd(xh, P, xt)
    assert pd.all()
    for k in kc.KEYS:
        np.testing.assert_allclose(got[k], ref[k], rtol=1e-9, err_msg=k)
    P[3] = -P[3]  # not positive definite: flagged (the engine's divergence check reads the flag)
    assert not kc.nees_and_pd(xh, P, xt)[1][3]


def test_attitude_chart_covariance_is_mapped_like_the_numpy_path():
    """An attitude-chart filter's ``P (n-1 x n-1)`` enters as ``M^-1 P M^-T`` (``aligned.from_attitude_chart``, two
    solves in numpy; ``T_aligned S_attitude`` in the kernel): the same NEES, and ``pd`` that of ``P`` itself."""
    from stereopose_mc.mc import trial

    xh, Pa, xt = _case(25, 4)
    P = aligned.to_attitude_chart(xh, Pa)  # an aligned covariance seen in the attitude chart
    assert np.abs(P - Pa).max() > 1e-3 * np.abs(Pa).max()  # really another matrix
    ref = trial.nees_of(xh, P, xt, "attitude", "numpy")
    got, pd = kc.nees_and_pd(xh, P, xt, attitude=True)
    assert pd.all()
    for k in kc.KEYS:
        np.testing.assert_allclose(got[k], ref[k], rtol=1e-9, err_msg=k)
        np.testing.assert_allclose(got[k], aligned.nees_report(xh, Pa, xt)[k], rtol=1e-9, err_msg=k)
    # the engine's entry point picks the mapping from the filter's error state
    eng, _ = trial.nees_and_pd(xh, P, xt, "attitude", "compiled")
    np.testing.assert_array_equal(eng["nees"], got["nees"])
    P[3] = -P[3]
    assert not kc.nees_and_pd(xh, P, xt, attitude=True)[1][3]


@pytest.mark.parametrize("N", [1, 3, 5, 20])
def test_error_map_from_its_non_zeros_equals_the_dense_product(N):
    """``aligned._apply_error_map`` (``T src`` from the non-zeros of ``T``, the point rows summed once) against
    numpy's ``aligned.error_map(x) @ src``, for the ``n`` and ``n - 1`` wide matrices it is given; and
    ``consistency._map_full`` (``T P T^T``) against the dense triple product, exactly symmetric."""
    from stereopose_mc.core.kernels import aligned as ka

    xh, _, _ = _case(6, N)
    n = xh.shape[-1]
    T = aligned.error_map(xh)
    Tm, Sp = np.empty((n - 1, n)), np.empty((3, n))
    for b in range(len(xh)):
        ka._error_map(xh[b], Tm)
        np.testing.assert_allclose(Tm, T[b], rtol=1e-14, atol=1e-15)
        for m in (n, n - 1):
            src = RNG.standard_normal((n, m)) * np.logspace(-3, 3, m)
            dst = np.empty((n - 1, m))
            ka._apply_error_map(Tm, N, src, dst, Sp[:, :m])
            want = T[b] @ src
            assert np.max(np.abs(dst - want) / np.abs(want).max(axis=0)) < 1e-14
        A = RNG.standard_normal((n, n))
        P = A @ A.T
        Pa = np.empty((n - 1, n - 1))
        kc._map_full(xh[b], P, Tm, np.empty((n - 1, n)), np.empty((n, n - 1)), Pa, Sp)
        want = T[b] @ P @ T[b].T
        d = np.sqrt(np.diag(want))
        assert np.max(np.abs(Pa - want) / np.outer(d, d)) < 1e-14
        np.testing.assert_array_equal(Pa, Pa.T)
        # lower: the lower triangle of the full product, bit for bit, and nothing above it written
        src = RNG.standard_normal((n, n - 1))
        full, low = np.empty((n - 1, n - 1)), np.full((n - 1, n - 1), 7.0)
        ka._apply_error_map(Tm, N, src, full, Sp[:, : n - 1])
        ka._apply_error_map(Tm, N, src, low, Sp[:, : n - 1], True)
        np.testing.assert_array_equal(np.tril(low), np.tril(full))
        assert (low[np.triu_indices(n - 1, 1)] == 7.0).all()


def _full_state_case(B, N, rng):
    xh, _, _ = _case(B, N)
    n = xh.shape[-1]
    A = rng.standard_normal((B, n, n))
    d = np.logspace(-2, 2, n)[rng.permutation(n)]  # standard deviations over four decades, correlated
    return xh, d[:, None] * (A @ A.transpose(0, 2, 1) / n + 0.1 * np.eye(n)) * d


def _numpy_pd(P):
    try:
        np.linalg.cholesky(P)
        return True
    except np.linalg.LinAlgError:
        return False


def _with_aligned_covariance(x, Pa, c, s):
    """A full-state ``P`` with ``T P T^T = Pa`` (``T = aligned.error_map(x)``), ``T P t = c`` and ``t^T P t = s``
    (``t = (0, q/|q|, 0)``, ``T t = 0``): ``P = E^-1 [[Pa, c], [c^T, s]] E^-T``, ``E = [T; t^T]`` invertible."""
    n = x.shape[-1]
    t = np.zeros(n)
    t[9:13] = x[9:13] / np.linalg.norm(x[9:13])
    E = np.vstack([aligned.error_map(x[None])[0], t])
    M = np.block([[Pa, c[:, None]], [c[None, :], np.array([[s]])]])
    Y = np.linalg.solve(E, M)  # E^-1 M
    P = np.linalg.solve(E, Y.T).T  # E^-1 M E^-T
    return 0.5 * (P + P.T)


@pytest.mark.parametrize("N", [1, 5, 12])
def test_preimage_maps_back_to_the_aligned_error(N):
    """``_preimage``: ``T dx = e`` for ``T = aligned.error_map(x)`` (numpy), with ``dx``'s quaternion part orthogonal
    to ``q`` (the null direction of ``T``)."""
    rng = np.random.default_rng(N)
    xh, _, _ = _case(6, N)
    n = xh.shape[-1]
    for b in range(len(xh)):
        T = aligned.error_map(xh[b : b + 1])[0]
        Tm, dx = np.empty((n - 1, n)), np.empty(n)
        kc._error_map(xh[b], Tm)
        e = rng.standard_normal(n - 1) * np.logspace(-3, 1, n - 1)
        kc._preimage(Tm, e, dx, N)
        np.testing.assert_allclose(T @ dx, e, rtol=1e-13, atol=1e-14)
        assert abs(dx[9:13] @ xh[b, 9:13]) <= 1e-15 * np.linalg.norm(dx[9:13]) * np.linalg.norm(xh[b, 9:13]) + 1e-300


def test_attitude_chart_map_of_the_aligned_map_is_the_attitude_error_map():
    """``M T = errorstate.error_map`` (``M = T_attitude S_aligned``, ``T = aligned.error_map``, all at ``x_hat``): the
    attitude chart's blocks of ``M T P T^T M^T`` are ``P``'s own diagonal blocks (and ``Xi P_qq Xi^T`` for the
    attitude), which ``_one_full`` reads without mapping ``P``."""
    from stereopose_mc.core import errorstate as es

    xh, _, _ = _case(10, 4)
    MT = es.error_map(xh) @ aligned.chart_jacobian(xh) @ aligned.error_map(xh)
    np.testing.assert_allclose(MT, es.error_map(xh), rtol=0, atol=1e-13)


@pytest.mark.parametrize("N", [1, 5, 12])
def test_full_state_nees_depends_on_the_aligned_covariance_only(N):
    """A full-state ``P`` enters the NEES only through ``T P T^T``: whatever its variance along the quaternion's norm
    ``s`` (1e-12 to 1e4 of the others: ``P`` up to ~1e14 ill-conditioned) and its correlation ``c`` with the rest,
    every NEES is that of numpy's ``aligned.nees_report`` with ``T P T^T``, and ``pd`` is numpy's Cholesky of ``P``."""
    rng = np.random.default_rng(N)
    xh, Pa, xt = _case(6, N)
    ne = xh.shape[-1] - 1
    for b in range(len(xh)):
        ref = aligned.nees_report(xh[b : b + 1], Pa[b : b + 1], xt[b : b + 1])
        for s, rho in ((1e-12, 0.0), (1e-12, 0.5), (1.0, 0.9), (1e4, 0.3)):
            scale = s * np.trace(Pa[b]) / ne
            v = rng.standard_normal(ne)
            c = rho * np.sqrt(scale) * (Pa[b] @ v) / np.sqrt(v @ Pa[b] @ v)  # |c|^2 < s c^T Pa^-1 c: PD
            P = _with_aligned_covariance(xh[b], Pa[b], c, scale)
            got, pd = kc.nees_and_pd(xh[b : b + 1], P[None], xt[b : b + 1])
            assert pd[0] == _numpy_pd(P)
            for k in kc.KEYS:
                np.testing.assert_allclose(got[k], ref[k], rtol=1e-8, err_msg=f"{k} s={s:g} rho={rho}")


@pytest.mark.parametrize("N", [1, 5, 12])
def test_full_state_pd_is_numpys_cholesky(N):
    """``pd`` of a full-state ``P`` is numpy's Cholesky of ``P`` (the one factorization the NEES is computed from), for
    covariances spread over four decades, then made indefinite along the quaternion's norm alone (which ``T P T^T``
    does not see: the NEES are then those of the mapped covariance, as in the numpy path) or in a direction ``T``
    sees too."""
    from stereopose_mc.mc import trial

    rng = np.random.default_rng(N)
    xh, P = _full_state_case(8, N, rng)
    xt = xh.copy()
    xt[:, :9] += 0.01 * rng.standard_normal((len(xh), 9))
    n = xh.shape[-1]
    for b in range(len(xh)):
        got, pd = kc.nees_and_pd(xh[b : b + 1], P[b][None], xt[b : b + 1])
        assert pd[0] and _numpy_pd(P[b])
        t = np.zeros(n)
        t[9:13] = xh[b, 9:13] / np.linalg.norm(xh[b, 9:13])
        Q = P[b] - 2.0 * (t @ P[b] @ t) * np.outer(t, t)  # t^T Q t < 0; T Q T^T = T P T^T
        got2, pd2 = kc.nees_and_pd(xh[b : b + 1], Q[None], xt[b : b + 1])
        assert not pd2[0] and not _numpy_pd(Q)
        ref = trial.nees_of(xh[b : b + 1], Q[None], xt[b : b + 1], "full", "numpy")
        for k in kc.KEYS:
            np.testing.assert_allclose(got2[k], ref[k], rtol=1e-8, err_msg=k)
            np.testing.assert_allclose(got2[k], got[k], rtol=1e-8, err_msg=k)
        v = rng.standard_normal(n)
        Q = P[b] - 1e3 * (v @ P[b] @ v) / (v @ v) ** 2 * np.outer(v, v)  # indefinite in a direction T sees too
        assert not _numpy_pd(Q) and not kc.nees_and_pd(xh[b : b + 1], Q[None], xt[b : b + 1])[1][0]


def test_attitude_chart_nees_blocks_are_those_of_its_own_covariance():
    """An attitude error state's ``P`` (``nees_and_pd(..., attitude=True)``, unmapped since stop 24): each block's
    NEES is ``eps_b^T P_bb^-1 eps_b`` with ``eps = errorstate.estimation_error`` and ``P``'s own diagonal block
    (``M (M^-1 P M^-T) M^T = P``), by numpy's solve; the full NEES is that of ``M^-1 P M^-T`` against the truth's
    aligned error (``aligned.nees_report``), also with ``P`` a thousand times wider along one direction."""
    from stereopose_mc.core import errorstate as es

    rng = np.random.default_rng(24)
    for N in (1, 4, 7):
        xh, Pa, xt = _case(12, N)
        P = aligned.to_attitude_chart(xh, Pa)
        v = rng.standard_normal(P.shape[-1])
        P[3:] += 1e3 * np.trace(P[3]) / P.shape[-1] * np.outer(v, v) / (v @ v)  # ill-conditioned (~1e5)
        got, pd = kc.nees_and_pd(xh, P, xt, attitude=True)
        assert pd.all()
        eps = es.estimation_error(xh, xt)
        for name, b in es.error_blocks(N).items():
            want = [eps[i, b] @ np.linalg.solve(P[i][b][:, b], eps[i, b]) for i in range(len(xh))]
            np.testing.assert_allclose(got[f"nees_{name}"], want, rtol=1e-9, err_msg=name)
        ref = aligned.nees_report(xh, aligned.from_attitude_chart(xh, P), xt)
        for k in ("nees", "nees_gauge"):
            np.testing.assert_allclose(got[k], ref[k], rtol=1e-8, err_msg=k)


def test_small_block_mahalanobis_is_the_general_one_bit_for_bit():
    """The 2 x 2 and 3 x 3 blocks' NEES in scalars (``_mahalanobis_small``) against ``_cholesky_small`` and
    ``_forward`` on the same block: the same bits, NaN where the block is not positive definite (and other sizes
    on the general path)."""
    from stereopose_mc.core.kernels import cholesky as kcho

    rng = np.random.default_rng(11)
    for m in (1, 2, 3, 4):  # 1 and 4: the general path on both sides, the boundaries of the scalar one
        for trial in range(300):
            A = rng.standard_normal((m, m)) * np.logspace(-4, 4, m)[rng.permutation(m)]
            C = A @ A.T if trial % 3 else A @ A.T - rng.uniform(0, 2) * np.trace(A @ A.T) * np.eye(m) / m
            e = rng.standard_normal(m) * 10.0 ** rng.uniform(-4, 4)
            L, w = np.zeros((m, m)), np.empty(m)
            want = np.nan
            if kcho._cholesky_small(C, L):
                kcho._forward(L, e, w)
                want = 0.0
                for i in range(m):  # the general path's order: a running sum of squares
                    want += w[i] * w[i]
            got = kc._mahalanobis(e, C, np.zeros((m, m)), np.empty(m))
            assert got == want or (np.isnan(got) and np.isnan(want)), (m, trial, got, want)


@pytest.mark.parametrize("m", [1, 4, 15, 24, 25, 60])
def test_points_block_mahalanobis(m):
    """``_mahalanobis_lapack`` (the points' block: written out by rows of ``U`` up to ``ROWS_MAX`` rows, ``potrf``
    past it) is ``e^T P^-1 e`` (numpy's solve, to round-off), NaN where ``P`` is not positive definite or not
    finite; ``cholesky._upper_rows`` gives numpy's Cholesky factor, transposed."""
    from stereopose_mc.core.kernels import cholesky as kcho

    rng = np.random.default_rng(40 + m)
    for trial in range(20):
        A = rng.standard_normal((m, 2 * m)) * np.logspace(-3, 3, m)[:, None]
        P = A @ A.T / m + 1e-6 * np.eye(m)
        e = rng.standard_normal(m)
        got = kc._mahalanobis_lapack(e, P, np.empty((m, m)), np.empty(m))
        want = float(e @ np.linalg.solve(P, e))
        assert got == pytest.approx(want, rel=1e-8), (m, trial)
        if m <= kc.ROWS_MAX:
            U = np.full((m, m), np.nan)
            assert kcho._upper_rows(P, U)
            np.testing.assert_allclose(U.T, np.linalg.cholesky(P), rtol=0, atol=1e-12 * np.sqrt(np.abs(P).max()))
            assert np.array_equal(np.tril(U, -1), np.zeros((m, m)))
    bad = P - 2.0 * np.abs(np.linalg.eigvalsh(P)).max() * np.eye(m)
    assert np.isnan(kc._mahalanobis_lapack(e, bad, np.empty((m, m)), np.empty(m)))
    nan = P.copy()
    nan[m // 2, m // 2] = np.nan
    assert np.isnan(kc._mahalanobis_lapack(e, nan, np.empty((m, m)), np.empty(m)))


def test_small_block_mahalanobis_reads_its_block_in_place():
    """``_mahalanobis_small(e, o, P, r, m)``: the NEES of ``e[o:o+m]`` with ``P[r:r+m, r:r+m]`` read in place, bit for
    bit that of the block copied out (the full-state NEES's rho, rho_dot, omega, attitude and k blocks)."""
    rng = np.random.default_rng(12)
    for trial in range(200):
        A = rng.standard_normal((9, 9))
        P = A @ A.T if trial % 4 else A @ A.T - 3.0 * np.eye(9)
        e = rng.standard_normal(9)
        for o, r, m in ((0, 0, 3), (3, 4, 3), (6, 1, 2), (7, 7, 2)):
            got = kc._mahalanobis_small(e, o, P, r, m)
            want = kc._mahalanobis(e[o : o + m].copy(), P[r : r + m, r : r + m].copy(), np.zeros((m, m)), np.empty(m))
            assert got == want or (np.isnan(got) and np.isnan(want)), (trial, o, r, m, got, want)


@pytest.mark.parametrize("N,centred", [(N, c) for c in (False, True) for N in (1, 2, 5, 8)])
def test_gauge_columns_are_solved_like_a_triangular_solve(N, centred):
    """``_gauge_forward``: ``U = L^-1 G`` for the three gauge columns (1 on each point's rows) in one pass, ``L``
    given as the square root ``R = J L^T`` (the compiled update's layout), against scipy's triangular solve; zero
    above the points' rows. ``centred``: the columns ``T G`` of the centred coordinates (``core.kernels.centred``'s
    ``T`` applied to ``G`` by ``_center_rows``: the unit vectors of the points' mean)."""
    from scipy.linalg import solve_triangular

    from stereopose_mc.core.kernels.centred import _center_rows

    ne = 14 + 3 * N
    A = RNG.standard_normal((ne, ne))
    L = np.linalg.cholesky(A @ A.T + ne * np.eye(ne))
    G = np.zeros((ne, 3))
    G[12 : 12 + 3 * N] = np.tile(np.eye(3), (N, 1))
    if centred:
        TG = np.zeros_like(G)
        _center_rows(G, TG, N)
        np.testing.assert_array_equal(TG, np.eye(ne, 3, -12))
        G = TG
    U = np.full((3, ne), np.nan)
    kc._gauge_forward(np.ascontiguousarray(L.T[::-1]), U, N, centred)
    want = solve_triangular(L, G, lower=True).T
    np.testing.assert_allclose(U, want, rtol=1e-13, atol=1e-15)
    assert np.all(U[:, :12] == 0.0)


@pytest.mark.parametrize("n", [1, 2, 15, 30, 41])
def test_square_root_layout_solves_and_factor(n):
    """The NEES's layout of ``P``'s factor: ``R = J U`` (``P = U^T U = R^T R``, the rows of the upper Cholesky factor
    reversed). ``_own_root`` builds it from ``P`` (``R^T R = P``, numpy's factor reversed; False where ``P`` is not
    positive definite); ``_forward_r`` and ``_forward5`` solve ``L x = b`` with ``L = U^T`` as scipy does;
    ``_factor_given`` accepts it and rejects a NaN marker at ``U[0, 0]`` or a non-positive pivot."""
    from scipy.linalg import solve_triangular

    M = RNG.standard_normal((n, n))
    P = M @ M.T + n * np.eye(n)
    Uf, R = np.empty((n, n)), np.empty((n, n))
    assert kc._own_root(P, Uf, R)
    L = np.linalg.cholesky(P)
    np.testing.assert_allclose(R, L.T[::-1], rtol=0, atol=1e-13 * np.abs(L).max())
    np.testing.assert_allclose(R.T @ R, P, rtol=0, atol=1e-12 * np.abs(P).max())
    b = RNG.standard_normal(n)
    out = np.empty(n)
    kc._forward_r(R, b, out)
    np.testing.assert_allclose(out, solve_triangular(L, b, lower=True), rtol=1e-12, atol=1e-14)
    W = RNG.standard_normal((5, n))
    W2 = W.copy()
    kc._forward5(R, W2)
    np.testing.assert_allclose(W2, solve_triangular(L, W.T, lower=True).T, rtol=1e-12, atol=1e-14)
    assert kc._factor_given(R)
    bad = R.copy()
    bad[n - 1, 0] = np.nan  # U[0, 0]: the update's marker of a factor not given
    assert not kc._factor_given(bad)
    bad = R.copy()
    bad[0, n - 1] = 0.0  # U[n-1, n-1]
    assert not kc._factor_given(bad)
    P[0, 0] = -1.0
    assert not kc._own_root(P, Uf, R)


def test_compiled_errors_equal_the_numpy_errors():
    """``consistency.errors`` (the engine's six errors on the compiled path) against ``mc.trial.errors``: the same
    numbers (to the last bit or two), a shared truth broadcast, NaN where the estimate is not finite."""
    from stereopose_mc.mc import trial

    for N in (1, 5, 20):
        xh, _, xt = _case(50, N)
        xh[:, 9:13] *= 1.0 + 0.01 * RNG.standard_normal((50, 1))  # not unit quaternions: both normalize
        xh[3, 0] = np.nan
        xh[4, 9] = np.inf
        with np.errstate(invalid="ignore"):  # numpy's normalization of the infinite quaternion
            got, want, one = kc.errors(xh, xt), trial.errors(xh, xt), trial.errors(xh, xt[0])
        assert got.shape == (50, 6)
        np.testing.assert_allclose(got, want, rtol=1e-14, atol=0)
        assert np.isnan(got[3, 0]) and np.isfinite(got[3, 1:]).all() and np.isnan(got[4, 3])
        np.testing.assert_allclose(kc.errors(xh, xt[0]), one, rtol=1e-14, atol=0)
        assert np.nanmax(got[:, 3]) > 1.0  # degrees: the attitude errors are not all tiny


@pytest.mark.parametrize("chart", ["aligned", "attitude", "full"])
def test_nees_from_a_given_square_root_equal_those_that_factorize_p(chart):
    """``nees_and_pd(..., P_factor=R)`` with ``R = J U`` (``P = U^T U``, as the compiled update gives it): the same
    NEES to round-off as factorizing ``P`` in the kernel, ``pd`` True; a trial whose factor is marked not given
    (NaN at ``U[0, 0]``) takes ``P``'s own factorization, so its NEES are those computed without any factor, bit for
    bit, and so is ``pd`` where ``P`` is not positive definite. A factor shaped unlike ``P`` is refused."""
    rng = np.random.default_rng(11)
    if chart == "full":
        xh, P = _full_state_case(12, 5, rng)
        xt = xh.copy()
        xt[:, :9] += 0.01 * rng.standard_normal((len(xh), 9))
    else:
        xh, P, xt = _case(12, 5)
        if chart == "attitude":
            P = aligned.to_attitude_chart(xh, P)
    attitude = chart == "attitude"
    P[3] = -P[3]  # not positive definite: no factor, pd False
    R = np.empty_like(P)
    for b in range(len(P)):
        R[b] = np.linalg.cholesky(P[b]).T[::-1] if b != 3 else np.nan
    R[5, -1, 0] = np.nan  # marked not given
    ref, pd_ref = kc.nees_and_pd(xh, P, xt, attitude)
    got, pd = kc.nees_and_pd(xh, P, xt, attitude, R)
    np.testing.assert_array_equal(pd, pd_ref)
    assert pd.sum() == len(P) - 1 and not pd[3]
    for k in kc.KEYS:
        np.testing.assert_allclose(got[k], ref[k], rtol=1e-9, err_msg=k)
        np.testing.assert_array_equal(got[k][[3, 5]], ref[k][[3, 5]], err_msg=k)
    with pytest.raises(ValueError, match="P_factor"):
        kc.nees_and_pd(xh, P, xt, attitude, R[:, 1:, 1:])


@pytest.mark.parametrize("n,m", [(30, 30), (30, 29), (135, 134)])
def test_nees_scratch_views_tile_their_buffers_without_overlap(n, m):
    """``_nees_scratch``'s 33 arrays are views into two buffers (two allocations per call of the update kernels):
    each C-contiguous, shaped as ``nees_batch`` used them, none overlapping another (a value written through one
    is read back from it after every other is written), the integer and zero-started ones zero."""
    ws = kc._nees_scratch(n, m)
    ne, k = n - 1, 3 + 3 * ((n - 15) // 3)
    shapes = [(ne, n), (n, ne), (ne, ne), (ne,), (ne, n), (n, ne), (3, n), (ne, ne), (m, m), (m, m), (ne, ne), (ne,),
              (ne,), (ne,), (ne, k), (ne, k), (ne, ne), (ne, ne), (ne, ne), (ne,), (3, ne), (ne,), (ne, ne), (3, 3),
              (3, 3), (3, 3), (4,), (4,), (6, 3), (3, ne), (6, 3), (5, n), (kc.N_AXES,)]  # fmt: skip
    assert [a.shape for a in ws] == shapes
    assert all(a.flags.c_contiguous for a in ws)
    assert not ws[3].any() and not ws[13].any() and not ws[14].any() and not ws[15].any()  # e0, cnt, cols, vals
    assert ws[13].dtype == ws[14].dtype == np.int64
    for i, a in enumerate(ws):
        a[...] = i + 1
    for i, a in enumerate(ws):
        assert (a == i + 1).all(), i


def test_a_diagonal_covariance_is_factorized_as_potrf_does():
    """``_own_root``'s fast path for a diagonal ``P`` (the initial covariance): the same bits as ``potrf``'s factor
    (``_cholesky_upper``), reversed; the same refusals (a zero, negative, infinite or NaN variance); a ``P`` with one
    off-diagonal entry takes ``potrf`` itself."""
    from stereopose_mc.core.kernels.cholesky import _cholesky_upper

    rng = np.random.default_rng(12)
    cases = [rng.random(30) * 10.0 ** rng.uniform(-9, 4, 30)] + [
        np.where(np.arange(6) == 2, bad, 1.0 + np.arange(6.0)) for bad in (0.0, -1.0, np.inf, np.nan)]
    for d in cases:
        n = d.size
        good = bool(np.all(d > 0) and np.all(np.isfinite(d)))
        Ps = [np.diag(d)] + ([np.diag(d) + np.eye(n, k=-1) * 1e-3 * d.min()] if good else [])
        for P in Ps:
            R, U, U2 = np.full((n, n), 7.0), np.empty((n, n)), np.empty((n, n))
            got, want = kc._own_root(P, U, R), _cholesky_upper(P, U2)
            assert got == want == good
            if got:
                np.testing.assert_array_equal(R, U2[::-1])
    assert kc._diagonal(np.diag(cases[0])) and not kc._diagonal(np.diag(cases[0]) + np.eye(30, k=-29))


def test_finite_is_numpys_isfinite_on_every_kind_of_float():
    """``consistency._finite`` (a count of exponent-bit tests) is ``np.isfinite(v).all()``: infinities and NaNs of
    either sign or payload anywhere, the largest and the subnormal floats, zeros of both signs."""
    from stereopose_mc.core.kernels.consistency import _finite

    rng = np.random.default_rng(3)
    nan_payload = np.array([0x7FF8000000000001, 0xFFF0000000000001], np.uint64).view(np.float64)  # quiet, signalling
    special = np.concatenate([[np.inf, -np.inf, np.nan, -np.nan], nan_payload])
    ordinary = [np.finfo(float).max, -np.finfo(float).max, 5e-324, -5e-324, np.finfo(float).tiny, 0.0, -0.0, 1.0]
    for n in (1, 3, 30, 900, 901):
        v = rng.standard_normal(n) * 1e200
        assert _finite(v)
        for x in ordinary:
            w = v.copy()
            w[rng.integers(n)] = x
            assert _finite(w)
        for x in special:
            for i in {0, n // 2, n - 1}:
                w = v.copy()
                w[i] = x
                assert not _finite(w) and not np.isfinite(w).all()


@settings(max_examples=40, deadline=None)
@given(N=st_h.integers(1, 30), scale=st_h.floats(-6.0, 3.0), seed=st_h.integers(0, 2**32 - 1))
def test_the_points_block_from_the_points_is_blocks_sum_bit_for_bit(N, scale, seed):
    """``_point_block`` (the points' rows of ``M`` written from ``x_hat``'s points, ``d P_i = e_Pi + [P_i x] delta``)
    gives ``_block``'s ``Y = M_pts P`` and ``C = M_pts P M_pts^T`` on the rows of ``_attitude_rows`` bit for bit, at
    any number of points and scale (the same terms added to 0 in the same order), and ``C`` is
    ``M_pts P M_pts^T`` (dense, numpy) to round-off."""
    from stereopose_mc.core.layout import E_POINTS, E_ROT, VEC

    rng = np.random.default_rng(seed)
    n = 15 + VEC * N
    ne = n - 1
    xh = rng.standard_normal(n) * 10.0 ** rng.uniform(-2, 2, n)
    k = VEC + VEC * N
    cnt, cols, vals = np.zeros(ne, np.int64), np.zeros((ne, k), np.int64), np.zeros((ne, k))
    kc._attitude_rows(xh, N, rng.standard_normal((3, 3)), rng.standard_normal(3), cnt, cols, vals, np.zeros((6, 3)))
    A = rng.standard_normal((ne, ne)) * 10.0**scale
    P = A @ A.T
    lo, hi = E_POINTS, E_POINTS + VEC * N
    Y1, C1 = np.full((ne, ne), np.nan), np.full((ne, ne), np.nan)
    Y2, C2 = Y1.copy(), C1.copy()
    kc._block(cnt, cols, vals, lo, hi, P, Y1, C1, E_ROT, hi)
    kc._point_block(xh, N, P, Y2, C2)
    m = hi - lo
    np.testing.assert_array_equal(Y2[:m, E_ROT:hi], Y1[:m, E_ROT:hi])
    np.testing.assert_array_equal(C2[:m, :m], C1[:m, :m])
    M = np.zeros((m, ne))
    for r in range(m):
        M[r, cols[lo + r, : cnt[lo + r]]] = vals[lo + r, : cnt[lo + r]]
    ref = M @ P @ M.T
    np.testing.assert_allclose(C2[:m, :m], ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())
