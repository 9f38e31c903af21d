"""Compiled (Numba) EKF and IEKF measurement updates on the row-sparse ``H`` of the model.

Twins of ``core.kalman.ekf_update`` and ``core.kalman.iekf_update`` (whose docstrings give
the equations), fused with the measurement model of ``core.kernels.model`` and run one
trial at a time: every product with ``H`` touches only the 16 non-zero columns of a row
(a feature's rows see ``rho, rho_dot, omega, q`` and its own point; the pseudo rows
``omega, q, k``), the symmetric positive definite systems (``S`` for the EKF, the whitened
``A = I + Hw^T Hw`` for the IEKF, ``P-`` itself) are solved by small hand-written Cholesky
factorizations; ``P+`` is the Joseph form of the numpy path evaluated for the optimal gain
(``P - W^T W`` for the EKF, ``L A^-1 L^T`` for the IEKF, positive semi-definite by
construction: the same matrix to round-off, exactly symmetric); the IEKF's iterations,
line search (MAP cost, step halving) and unit-free stopping test run per trial.

Both kernels take the filter's ``chart``: 0, the full state (``filters.relnav``: ``x + dx``,
quaternion renormalized); 1, the aligned error state (``filters.mekf`` with
``core.aligned``: prior ``e = 0`` with the error-state ``P``, ``h(x- [+] e)``, the row-sparse
``H_e`` of ``core.kernels.aligned`` whose virtual columns are served by the point sums
appended to ``P`` or ``L`` (``_with_virtual``), reset ``x+ = x- [+] e+``).

A measurement row with ``mask = False`` (a feature dropped by the tracker or rejected by
the gate) is taken out of the update exactly as ``filters.gating.masked_measure`` does:
``h = y`` and ``H = 0`` on that row.

Each kernel returns ``ok (B,)``: False where a Cholesky factorization failed (the numpy
path raises ``LinAlgError`` there; the caller handles those trials the numpy way).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .aligned import E_POINTS, _chart, _measure_aligned, augment
from .model import NNZ, _combine, _measure_one, _mirror_lower

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")

STOPPING = {"mahalanobis": 0, "prior": 1, "scaled": 2, "raw": 3}
CONTROL = {"none": 0, "line_search": 1}


@njit(**_JIT)
def _cholesky(A, L):
    """Lower ``L`` with ``L L^T = A`` (only the lower triangle of ``A`` is read); False if not PD.

    LAPACK's ``potrf`` through ``np.linalg.cholesky`` (Numba's binding of the BLAS/LAPACK that
    scipy ships), which raises on a matrix that is not positive definite or not finite.
    """
    try:
        L[:, :] = np.linalg.cholesky(A)
    except Exception:  # Numba's LinAlgError (not positive definite, or not finite)
        return False
    return True


@njit(**_JIT)
def _cholesky_small(A, L):
    """``_cholesky`` written out (left-looking), for the small blocks where LAPACK's call costs more than the work.

    Row ``j`` of ``U = L^T`` (held in the upper triangle of ``L``, transposed at the end) is row
    ``j`` of ``A``'s upper triangle minus a combination of the rows above it, divided by the
    square root of its pivot.
    """
    n = A.shape[0]
    for i in range(n):
        for j in range(i, n):
            L[i, j] = A[j, i]
    for j in range(n):
        _combine(L[j], j, n, L, L[:, j], 0, j, -1.0)
        d = L[j, j]
        if not d > 0.0:
            return False
        d = math.sqrt(d)
        for c in range(j, n):
            L[j, c] /= d
    for i in range(n):
        for j in range(i):
            L[i, j] = L[j, i]
            L[j, i] = 0.0
    return True


@njit(**_JIT)
def _chol_solve(L, b):
    """``b <- (L L^T)^-1 b`` in place (``b`` a vector)."""
    n = L.shape[0]
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * b[k]
        b[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = b[i]
        for k in range(i + 1, n):
            s -= L[k, i] * b[k]
        b[i] = s / L[i, i]


@njit(**_JIT)
def _masked(hx, Hval, y, mask):
    """Rows out of the update: ``h = y``, ``H = 0``."""
    for r in range(hx.shape[0]):
        if not mask[r]:
            hx[r] = y[r]
            for k in range(NNZ):
                Hval[r, k] = 0.0


@njit(**_JIT)
def _measure_at(chart, xp, e, vis, baseline, disparity, focal, pseudo, alpha, nd, ndd, compute_jac, hx, Hval, xt, D,
                dD):  # fmt: skip
    """``h`` and the row-sparse ``H`` of one trial at ``x- [+] e`` in the filter's coordinates.

    ``chart`` 0: the full state, ``xt = x- + e``, ``H`` of ``model._measure_one``; 1: the aligned
    error state, ``xt = aligned.chart(x-, e)``, ``H_e`` of ``aligned._measure_aligned``.
    """
    if chart == 0:
        for i in range(xp.shape[0]):
            xt[i] = xp[i] + e[i]
        _measure_one(xt, vis, baseline, disparity, focal, pseudo, alpha, nd, ndd, compute_jac, hx, Hval, D, dD)
    else:
        _measure_aligned(xp, e, vis, baseline, disparity, focal, pseudo, alpha, nd, ndd, compute_jac, hx, Hval, xt,
                         D, dD)  # fmt: skip


@njit(**_JIT)
def _reset(chart, xp, e, out):
    """The posterior state ``x- [+] e``: ``x- + e`` with its quaternion renormalized (full), or ``aligned.chart``."""
    if chart == 0:
        for i in range(xp.shape[0]):
            out[i] = xp[i] + e[i]
        _normalize_q(out)
    else:
        _chart(xp, e, out, np.empty((3, 3)), np.empty((3, 3)), np.empty(3))


@njit(**_JIT)
def _with_virtual(chart, M, Maug):
    """``M`` with, in the aligned chart, the rows of the virtual columns appended (``aligned.augment``)."""
    if chart == 0:
        for i in range(M.shape[0]):
            for j in range(M.shape[1]):
                Maug[i, j] = M[i, j]
    else:
        augment(M, Maug)


@njit(**_JIT)
def ekf_update_batch(x, P, y, R, mask, vis, baseline, disparity, focal, pseudo, alpha, nd, ndd, cols, chart):
    """EKF update of every trial: ``S = H P H^T + R``, ``K = P H^T S^-1``, ``x+ = x [+] K nu``, ``P+``.

    ``chart`` 0: ``x``, ``P (B, n, n)`` of the full state (``relnav.update``); 1: ``P (B, n-1, n-1)``
    of the aligned error state at ``x`` (``mekf.update``: prior ``e = 0``, ``H_e``, reset
    ``x+ = x [+] e+``). ``P+`` is the Joseph form of ``kalman.ekf_update`` evaluated, for its
    optimal gain, as ``P - (Ls^-1 H P)^T (Ls^-1 H P)`` (``S = Ls Ls^T``): the same matrix to
    round-off, exactly symmetric, at a third of the cost.

    Returns ``(x+, P+, nu, nis, ok)``; in the full chart the quaternion of ``x+`` is renormalized.
    """
    B, n = x.shape
    ne = P.shape[1]
    nv = ne + (3 if chart == 1 else 0)  # columns of H, virtual ones included
    m = y.shape[1]
    xo = np.empty((B, n))
    Po = np.empty((B, ne, ne))
    nu = np.empty((B, m))
    nis = np.empty(B)
    ok = np.ones(B, np.bool_)
    hx = np.empty(m)
    Hval = np.zeros((m, NNZ))
    Paug = np.empty((nv, ne))
    HP = np.empty((m, nv))
    S = np.empty((m, m))
    Ls = np.empty((m, m))
    Z = np.empty((m, ne + 1))
    e = np.zeros(ne)
    xt = np.empty(n)
    D = np.empty((3, 3))
    dD = np.empty((4, 3, 3))
    for b in range(B):
        for i in range(ne):
            e[i] = 0.0
        _measure_at(chart, x[b], e, vis, baseline, disparity, focal, pseudo, alpha[b], nd, ndd, True, hx, Hval, xt,
                    D, dD)  # fmt: skip
        _masked(hx, Hval, y[b], mask[b])
        _with_virtual(chart, P[b], Paug)
        for r in range(m):
            nu[b, r] = y[b, r] - hx[r]
            for j in range(ne):
                HP[r, j] = 0.0
            for k in range(NNZ):
                h = Hval[r, k]
                if h != 0.0:
                    c = cols[r, k]
                    for j in range(ne):
                        HP[r, j] += h * Paug[c, j]
        if chart == 1:  # H P's virtual columns: the sums over the points
            for r in range(m):
                for a in range(3):
                    s = 0.0
                    for p in range((ne - 14) // 3):
                        s += HP[r, E_POINTS + 3 * p + a]
                    HP[r, ne + a] = s
        for r in range(m):
            for q in range(r + 1):
                s = 0.0
                for k in range(NNZ):
                    s += HP[r, cols[q, k]] * Hval[q, k]
                S[r, q] = s
            S[r, r] += R[b, r]
        if not _cholesky(S, Ls):
            ok[b] = False
            continue
        # W = Ls^-1 [H P | nu] (forward substitution by rows): with K = P H^T S^-1,
        # K nu = W[:, :n]^T W[:, n], nis = |W[:, n]|^2 and the Joseph form with this optimal gain,
        # (I - K H) P (I - K H)^T + K R K^T = P - K S K^T = P - W[:, :n]^T W[:, :n]
        for r in range(m):
            for j in range(ne):
                Z[r, j] = HP[r, j]
            Z[r, ne] = nu[b, r]
            _combine(Z[r], 0, ne + 1, Z, Ls[r], 0, r, -1.0)
            d = Ls[r, r]
            for j in range(ne + 1):
                Z[r, j] /= d
        v = 0.0
        for r in range(m):
            v += Z[r, ne] * Z[r, ne]
        _combine(e, 0, ne, Z, Z[:, ne], 0, m, 1.0)
        Pb = Po[b]
        for i in range(ne):
            for j in range(i + 1):
                Pb[i, j] = P[b, i, j]
            _combine(Pb[i], 0, i + 1, Z, Z[:, i], 0, m, -1.0)
        _mirror_lower(Pb)
        nis[b] = v
        _reset(chart, x[b], e, xo[b])
    return xo, Po, nu, nis, ok


@njit(**_JIT)
def _normalize_q(x):
    qn = math.sqrt(x[9] * x[9] + x[10] * x[10] + x[11] * x[11] + x[12] * x[12])
    for i in range(9, 13):
        x[i] = x[i] / qn


@njit(**_JIT)
def _whiten(hx, Hval, cols, yb, rws, L, Hw, rw, A, Hd):
    """``Hw = R^-1/2 H L``, ``rw = R^-1/2 (y - h)``, ``A = I + Hw^T Hw`` (full, symmetric).

    ``R^-1/2 H`` is scattered into the dense ``Hd (m, n + virtual)`` and multiplied by ``L``
    (its rows past ``n``, those of the virtual columns, ``_with_virtual``) by BLAS, as is
    ``Hw^T Hw`` (``np.dot``); ``A``'s lower triangle is mirrored (exactly symmetric).
    """
    m, n = Hw.shape
    for r in range(m):
        rw[r] = (yb[r] - hx[r]) * rws[r]
        for j in range(Hd.shape[1]):
            Hd[r, j] = 0.0
        s = rws[r]
        for k in range(NNZ):
            h = Hval[r, k]
            if h != 0.0:
                Hd[r, cols[r, k]] += h * s
    np.dot(Hd, L, Hw)  # BLAS gemm
    np.dot(Hw.T, Hw, A)
    for i in range(n):
        A[i, i] += 1.0
    _mirror_lower(A)


@njit(**_JIT)
def _cost_at(chart, z, xp, L, yb, rws, mask, vis, baseline, disparity, focal, pseudo, alpha, nd, ndd, e, xt, hx,
             Hdummy, D, dD):  # fmt: skip
    """MAP cost ``|z|^2 + |R^-1/2 (y - h(x- [+] L z))|^2`` (``h`` only)."""
    _lower_mul(L, z, e)
    _measure_at(chart, xp, e, vis, baseline, disparity, focal, pseudo, alpha, nd, ndd, False, hx, Hdummy, xt, D, dD)
    c = 0.0
    for i in range(z.shape[0]):
        c += z[i] * z[i]
    for r in range(hx.shape[0]):
        if mask[r]:
            e = (yb[r] - hx[r]) * rws[r]
            c += e * e
    return c


@njit(**_JIT)
def _keep_linearization(A, Afin):
    """Copy the iterate's ``A = I + Hw^T Hw`` (that of the last accepted step gives ``P+``)."""
    Afin[:, :] = A


@njit(**_JIT)
def _mul_t(M, v, out):
    """``out = M^T v`` (``M (m, n)``), row by row."""
    m, n = M.shape
    for i in range(n):
        out[i] = 0.0
    for r in range(m):
        a = v[r]
        for i in range(n):
            out[i] += M[r, i] * a


@njit(**_JIT)
def _posterior_covariance(L, LA, out, X):
    """``out = L A^-1 L^T`` with ``A = LA LA^T``: ``X = LA^-1 L^T`` (forward substitution by rows), ``out = X^T X``
    (BLAS, lower triangle mirrored: exactly symmetric)."""
    n = L.shape[0]
    for i in range(n):
        for j in range(n):
            X[i, j] = L[j, i]
        _combine(X[i], 0, n, X, LA[i], 0, i, -1.0)
        d = LA[i, i]
        for j in range(n):
            X[i, j] /= d
    np.dot(X.T, X, out)  # BLAS gemm
    _mirror_lower(out)


@njit(**_JIT)
def _lower_mul(L, z, out):
    """``out = L z`` (``L`` lower triangular)."""
    for i in range(L.shape[0]):
        s = 0.0
        for j in range(i + 1):
            s += L[i, j] * z[j]
        out[i] = s


@njit(**_JIT)
def iekf_update_batch(x, P, y, R, mask, vis, baseline, disparity, focal, pseudo, alpha, nd, ndd, cols, chart,
                      tol, max_iter, control, stopping, max_halvings):  # fmt: skip
    """Gauss-Newton IEKF in whitened coordinates ``x = x- [+] L z`` (``kalman.iekf_update``), per trial.

    ``chart`` as in ``ekf_update_batch`` (1: the iterates are ``aligned.chart(x-, L z)``, ``P`` that
    of the aligned error state, as ``mekf.update``); ``control``: 0 none, 1 line search;
    ``stopping``: 0 mahalanobis, 1 prior, 2 scaled, 3 raw. Returns ``(x+, P+, nu, nis,
    iterations, converged, ok)``; in the full chart the quaternion of ``x+`` is renormalized.
    """
    B, nx = x.shape
    n = P.shape[1]  # the filter's coordinates: the full state, or the error state
    m = y.shape[1]
    xo = np.empty((B, nx))
    Po = np.empty((B, n, n))
    nu = np.empty((B, m))
    nis = np.empty(B)
    its = np.zeros(B, np.int64)
    conv = np.zeros(B, np.bool_)
    ok = np.ones(B, np.bool_)
    hx = np.empty(m)
    Hval = np.zeros((m, NNZ))
    Hdummy = np.zeros((m, NNZ))
    L = np.empty((n, n))
    Laug = np.empty((n + (3 if chart == 1 else 0), n))
    Hw = np.empty((m, n))
    Hd = np.empty((m, n + (3 if chart == 1 else 0)))
    rw = np.empty(m)
    v = np.empty(m)
    A = np.empty((n, n))
    Afin = np.empty((n, n))
    LA = np.empty((n, n))
    rws = np.empty(m)
    z = np.zeros(n)
    zn = np.empty(n)
    zt = np.empty(n)
    d = np.empty(n)
    g = np.empty(n)
    xt = np.empty(nx)
    dx = np.empty(n)
    e = np.empty(n)
    T = np.empty((n, n))
    D = np.empty((3, 3))
    dD = np.empty((4, 3, 3))
    for b in range(B):
        xp = x[b]
        yb = y[b]
        mk = mask[b]
        for r in range(m):
            rws[r] = 1.0 / math.sqrt(R[b, r])
        if not _cholesky(P[b], L):
            ok[b] = False
            continue
        _with_virtual(chart, L, Laug)
        for i in range(n):
            e[i] = 0.0
        _measure_at(chart, xp, e, vis, baseline, disparity, focal, pseudo, alpha[b], nd, ndd, True, hx, Hval, xt,
                    D, dD)  # fmt: skip
        _masked(hx, Hval, yb, mk)
        _whiten(hx, Hval, cols, yb, rws, Laug, Hw, rw, A, Hd)
        for r in range(m):
            nu[b, r] = yb[r] - hx[r]
        # NIS by Woodbury: |rw|^2 - g^T A^-1 g, g = Hw^T rw
        if not _cholesky(A, LA):
            ok[b] = False
            continue
        c0 = 0.0
        for r in range(m):
            c0 += rw[r] * rw[r]
        _mul_t(Hw, rw, g)
        for i in range(n):
            d[i] = g[i]
        _chol_solve(LA, d)
        s = 0.0
        for i in range(n):
            s += g[i] * d[i]
        nis[b] = c0 - s
        cost = c0
        for i in range(n):
            z[i] = 0.0
        _keep_linearization(A, Afin)
        failed = False
        fresh = True
        for it in range(max_iter):
            # z_GN = A^-1 Hw^T (rw + Hw z)
            for r in range(m):
                s = rw[r]
                for j in range(n):
                    s += Hw[r, j] * z[j]
                v[r] = s
            _mul_t(Hw, v, zn)
            if it > 0 and not _cholesky(A, LA):
                failed = True
                break
            fresh = True  # LA is the factor of this iterate's A
            _chol_solve(LA, zn)
            accepted = True
            c_new = cost
            if control == 1:  # backtracking line search on the MAP cost
                for i in range(n):
                    d[i] = zn[i] - z[i]
                a = 1.0
                accepted = False
                for _h in range(max_halvings + 1):
                    for i in range(n):
                        zt[i] = z[i] + a * d[i]
                    ct = _cost_at(chart, zt, xp, L, yb, rws, mk, vis, baseline, disparity, focal, pseudo, alpha[b], nd,
                                  ndd, e, xt, hx, Hdummy, D, dD)  # fmt: skip
                    if math.isfinite(ct) and ct <= cost:
                        accepted = True
                        c_new = ct
                        for i in range(n):
                            zn[i] = zt[i]
                        break
                    a *= 0.5
                if not accepted:
                    for i in range(n):
                        zn[i] = z[i]
            its[b] += 1
            # size of the increment dz = zn - z
            size = 0.0
            if stopping == 0:
                for i in range(n):
                    size += (zn[i] - z[i]) ** 2
                for r in range(m):
                    s = 0.0
                    for j in range(n):
                        s += Hw[r, j] * (zn[j] - z[j])
                    size += s * s
                size = math.sqrt(size)
            elif stopping == 1:
                for i in range(n):
                    size += (zn[i] - z[i]) ** 2
                size = math.sqrt(size)
            else:
                for i in range(n):
                    s = 0.0
                    for j in range(i + 1):
                        s += L[i, j] * (zn[j] - z[j])
                    dx[i] = s
                if stopping == 2:
                    for i in range(n):
                        size = max(size, abs(dx[i]) / math.sqrt(P[b, i, i]))
                else:
                    for i in range(n):
                        size += dx[i] * dx[i]
                    size = math.sqrt(size)
            small = accepted and size < tol
            if accepted:
                _keep_linearization(A, Afin)
            else:
                fresh = False  # Afin is an earlier iterate's: factorize it again below
            for i in range(n):
                z[i] = zn[i]
            cost = c_new
            if small:
                conv[b] = True
            if small or (control == 1 and not accepted) or it == max_iter - 1:
                break
            _lower_mul(L, z, e)
            _measure_at(chart, xp, e, vis, baseline, disparity, focal, pseudo, alpha[b], nd, ndd, True, hx, Hval, xt,
                        D, dD)  # fmt: skip
            _masked(hx, Hval, yb, mk)
            _whiten(hx, Hval, cols, yb, rws, Laug, Hw, rw, A, Hd)
        if failed or not (fresh or _cholesky(Afin, LA)):
            ok[b] = False
            continue
        _lower_mul(L, z, e)
        _reset(chart, xp, e, xo[b])
        # P+ = L A^-1 L^T = M M^T, M = L LA^-T: the Joseph form (I - K H) P- (I - K H)^T + K R K^T
        # of kalman.iekf_update with its optimal gain K = L A^-1 Hw^T R^-1/2 at the same H
        _posterior_covariance(L, LA, Po[b], T)
    return xo, Po, nu, nis, its, conv, ok
