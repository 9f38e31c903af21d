"""Compiled (Numba) EKF and IEKF measurement updates on the row-sparse ``H`` of the model.

Twins of ``core.kalman.ekf_update`` and ``core.kalman.iekf_update`` (whose docstrings give
the equations), fused with the measurement model of ``core.kernels.model`` and run one
trial at a time: every product with ``H`` touches only the 16 non-zero columns of a row
(a feature's rows see ``rho, rho_dot, omega, q`` and its own point; the pseudo rows
``omega, q, k``), the symmetric positive definite systems (the whitened ``A = I + Hw^T Hw``
of both updates, the EKF being one Gauss-Newton step of the IEKF, and ``P-`` itself) are
solved by Cholesky factorizations (LAPACK's ``potrf`` in place, ``_cholesky``); ``P+`` is the
Joseph form of the numpy path evaluated for the optimal gain (``L A^-1 L^T``, positive
semi-definite by construction: the same matrix to round-off, exactly symmetric); the IEKF's iterations,
step control (line search on the MAP cost with step halving, or Levenberg-Marquardt's damped
steps) and unit-free stopping test run per trial.

Both kernels take the filter's ``chart``: 0, the full state (``filters.relnav``: ``x + dx``,
quaternion renormalized); 1, the aligned error state (``filters.mekf`` with
``core.aligned``: prior ``e = 0`` with the error-state ``P``, ``h(x- [+] e)``, the row-sparse
``H_e`` of ``core.kernels.aligned`` whose virtual columns are served by the point sums
appended to ``P`` or ``L`` (``_with_virtual``), reset ``x+ = x- [+] e+``); 2, the attitude
error state (``filters.mekf`` with ``core.errorstate``: the same, with the row-sparse ``H_e`` of
``core.kernels.attitude`` and no virtual columns).

A measurement row with ``mask = False`` (a feature dropped by the tracker or rejected by
the gate) is taken out of the update exactly as ``filters.gating.masked_measure`` does:
``h = y`` and ``H = 0`` on that row.

Each kernel returns ``ok (B,)``: False where a Cholesky factorization failed (the numpy
path raises ``LinAlgError`` there; the caller handles those trials the numpy way).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types

from . import attitude as _att
from .aligned import _chart, _measure_aligned, augment
from .model import NNZ, _combine, _dot, _dot_row, _measure_one, _mirror_lower

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")

STOPPING = {"mahalanobis": 0, "prior": 1, "scaled": 2, "raw": 3}
CONTROL = {"none": 0, "line_search": 1, "levenberg_marquardt": 2}
SOLVE_BLOCK = 32  # past this size, triangular solves and Gram products run by blocks (BLAS on the blocks)


# LAPACK's dpotrf as Numba's own ``np.linalg.cholesky`` calls it (its C helper resolves scipy's
# ``cython_lapack`` at run time, so a cached kernel stays valid in a new process); called directly
# it factorizes in place: no copy of the input, no allocated output, no exception to catch.
_xxpotrf = types.ExternalFunction("numba_xxpotrf", types.intc(types.char, types.char, types.intp,
                                                               types.CPointer(types.float64), types.intp))  # fmt: skip
_KIND_D, _UPLO_U = 100, 85  # ord("d") (float64), ord("U")


@njit(**_JIT)
def _cholesky(A, L):
    """Lower ``L`` with ``L L^T = A`` (only the lower triangle of ``A`` is read); False if not PD.

    LAPACK's ``potrf`` on ``L`` in place (``L`` may be a block ``M[:m, :m]`` of a larger C-order
    array): a C-order lower triangle is the upper triangle of the same memory read in Fortran
    order, hence ``uplo = "U"``. ``potrf`` fails (``info > 0``) on a matrix that is not positive
    definite or meets a NaN pivot; an infinite pivot is caught by the check of the diagonal.
    """
    n = A.shape[0]
    for i in range(n):
        for j in range(i + 1):
            L[i, j] = A[i, j]
        for j in range(i + 1, n):
            L[i, j] = 0.0
    if n == 0:
        return True
    if L.strides[1] == 8:  # unit-stride rows: in place; a block ``L[:m, :m]``'s row stride is the leading dimension
        info = _xxpotrf(_KIND_D, _UPLO_U, n, L.ctypes, L.strides[0] // 8)
    else:  # (never in these kernels) a contiguous copy; no recursive call: a cached recursion does not link
        Lc = np.ascontiguousarray(L)
        info = _xxpotrf(_KIND_D, _UPLO_U, n, Lc.ctypes, n)
        L[:, :] = Lc
    if info != 0:
        return False
    for i in range(n):
        if not math.isfinite(L[i, i]):
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
def _forward(L, b, out, lo=0):
    """``out = L^-1 b`` (``L`` lower triangular, forward substitution; ``out`` may be ``b``).

    ``lo``: ``b[:lo]`` is zero, so ``out[:lo]`` is too and the sums start at ``lo`` (the same
    numbers as from 0 when ``lo`` is a multiple of 4: the terms skipped are exact zeros, and
    ``_dot_row``'s four partial sums keep their terms).
    """
    n = L.shape[0]
    for i in range(lo):
        out[i] = 0.0
    for i in range(lo, n):
        if i < 16:  # short rows (the NEES's small blocks): one running sum costs less than four
            t = b[i]
            for k in range(lo, i):
                t -= L[i, k] * out[k]
        else:
            t = b[i] - _dot_row(L, i, out, lo, i)
        out[i] = t / L[i, i]


@njit(**_JIT)
def _chol_solve(L, b):
    """``b <- (L L^T)^-1 b`` in place (``b`` a vector)."""
    n = L.shape[0]
    _forward(L, b, b)
    # L^T x = b from the last row up, by rows of L (contiguous): x_i = b_i / L_ii, then b_k -= L_ik x_i, k < i
    for i in range(n - 1, -1, -1):
        xi = b[i] / L[i, i]
        b[i] = xi
        Li = L[i]
        for k in range(i):
            b[k] -= Li[k] * xi


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
    error state, ``xt = aligned.chart(x-, e)``, ``H_e`` of ``aligned._measure_aligned``; 2: the
    attitude error state, ``xt = errorstate.chart(x-, e)``, ``H_e`` of ``attitude._measure_attitude``.
    """
    if chart == 0:
        for i in range(xp.shape[0]):
            xt[i] = xp[i] + e[i]
        _measure_one(xt, vis, baseline, disparity, focal, pseudo, alpha, nd, ndd, compute_jac, hx, Hval, D, dD)
    elif chart == 1:
        _measure_aligned(xp, e, vis, baseline, disparity, focal, pseudo, alpha, nd, ndd, compute_jac, hx, Hval, xt,
                         D, dD)  # fmt: skip
    else:
        _att._measure_attitude(xp, e, vis, baseline, disparity, focal, pseudo, alpha, nd, ndd, compute_jac, hx, Hval,
                               xt, D, dD)  # fmt: skip


@njit(**_JIT)
def _reset(chart, xp, e, out):
    """The posterior state ``x- [+] e``: ``x- + e`` with its quaternion renormalized (full), ``aligned.chart`` or
    ``errorstate.chart``."""
    if chart == 0:
        for i in range(xp.shape[0]):
            out[i] = xp[i] + e[i]
        _normalize_q(out)
    elif chart == 1:
        _chart(xp, e, out, np.empty((3, 3)), np.empty((3, 3)), np.empty(3))
    else:
        _att._chart(xp, e, out)


@njit(**_JIT)
def _with_virtual(chart, M, Maug):
    """``M`` with, in the aligned chart, the rows of the virtual columns appended (``aligned.augment``)."""
    if chart == 1:
        augment(M, Maug)
    else:
        for i in range(M.shape[0]):
            for j in range(M.shape[1]):
                Maug[i, j] = M[i, j]


def ekf_update_batch(x, P, y, R, mask, vis, baseline, disparity, focal, pseudo, alpha, nd, ndd, cols, chart):
    """EKF update of every trial: ``S = H P H^T + R``, ``K = P H^T S^-1``, ``x+ = x [+] K nu``, ``P+``.

    ``chart`` 0: ``x``, ``P (B, n, n)`` of the full state (``relnav.update``); 1: ``P (B, n-1, n-1)``
    of the aligned error state at ``x`` (``mekf.update``: prior ``e = 0``, ``H_e``, reset
    ``x+ = x [+] e+``); 2: the same in the attitude error state. Evaluated as one Gauss-Newton
    step of ``iekf_update_batch`` from the prior (whitened, ``P = L L^T``, ``Hw = R^-1/2 H L``,
    ``A = I + Hw^T Hw``): by the matrix inversion lemma ``L A^-1 Hw^T R^-1/2 = P H^T S^-1 = K``,
    ``L A^-1 L^T = P - K S K^T`` (the Joseph form of ``kalman.ekf_update`` for its optimal gain)
    and ``nu^T S^-1 nu = |rw|^2 - g^T A^-1 g``: the same numbers to round-off, with an
    ``n x n`` system instead of the ``m x m`` one (``m = 8N + 3 > n = 3N + 15``).

    A Python call of the compiled ``iekf_update_batch`` with one plain Gauss-Newton step (not a
    kernel of its own: that was a second copy of the same machine code to load at start-up).

    Returns ``(x+, P+, nu, nis, ok)``; in the full chart the quaternion of ``x+`` is renormalized.
    """
    xo, Po, nu, nis, _, _, ok = iekf_update_batch(x, P, y, R, mask, vis, baseline, disparity, focal, pseudo, alpha,
                                                  nd, ndd, cols, chart, 0.0, 1, 0, 1, 0)  # fmt: skip
    return xo, Po, nu, nis, ok


@njit(**_JIT)
def _normalize_q(x):
    qn = math.sqrt(x[9] * x[9] + x[10] * x[10] + x[11] * x[11] + x[12] * x[12])
    for i in range(9, 13):
        x[i] = x[i] / qn


@njit(**_JIT)
def _whiten(hx, Hval, cols, yb, rws, L, Hw, rw, A):
    """``Hw = R^-1/2 H L``, ``rw = R^-1/2 (y - h)``, ``A = I + Hw^T Hw`` (full, symmetric).

    Row by row: ``Hw[r] = sum_k H[r, c_k] L[c_k, :c_k+1]`` (``L`` lower triangular; its rows
    past ``n``, those of virtual columns, ``_with_virtual``, are read in full); then
    ``A = I + Hw^T Hw`` by BLAS (``np.dot``), its lower triangle mirrored (exactly symmetric).
    """
    m, n = Hw.shape
    for r in range(m):
        rw[r] = (yb[r] - hx[r]) * rws[r]
        for j in range(n):
            Hw[r, j] = 0.0
        for k in range(0, NNZ, 4):  # four columns of H per pass (L[c, j] = 0 past j = c)
            s = rws[r]
            h0, h1, h2, h3 = Hval[r, k] * s, Hval[r, k + 1] * s, Hval[r, k + 2] * s, Hval[r, k + 3] * s
            if h0 != 0.0 or h1 != 0.0 or h2 != 0.0 or h3 != 0.0:
                c0, c1, c2, c3 = cols[r, k], cols[r, k + 1], cols[r, k + 2], cols[r, k + 3]
                for j in range(min(max(max(c0, c1), max(c2, c3)) + 1, n)):
                    Hw[r, j] += (h0 * L[c0, j] + h1 * L[c1, j]) + (h2 * L[c2, j] + h3 * L[c3, j])
    _gram_lower(Hw, A)
    for i in range(n):
        A[i, i] += 1.0
    _mirror_lower(A)


@njit(**_JIT)
def _gram_lower(M, G):
    """The lower triangle of ``G = M^T M`` (``M (m, n)``) by BLAS: one product up to ``SOLVE_BLOCK`` columns,
    else the blocks on and below the diagonal only (about half the flops of the full product)."""
    m, n = M.shape
    nb = SOLVE_BLOCK
    if n <= nb:
        np.dot(M.T, M, G)
        return
    MT = np.ascontiguousarray(M.T)
    tmp = np.empty((nb, nb))
    for i0 in range(0, n, nb):
        i1 = min(i0 + nb, n)
        for j0 in range(0, i0 + 1, nb):
            j1 = min(j0 + nb, n)
            t = tmp[: i1 - i0, : j1 - j0]
            if i1 - i0 == nb and j1 - j0 == nb:
                np.dot(MT[i0:i1], MT[j0:j1].T, tmp)
            else:
                t2 = np.empty((i1 - i0, j1 - j0))
                np.dot(MT[i0:i1], MT[j0:j1].T, t2)
                t = t2
            for i in range(i0, i1):
                for j in range(j0, min(j1, i + 1)):
                    G[i, j] = t[i - i0, j - j0]


@njit(**_JIT)
def _cost_at(chart, z, xp, L, yb, rws, mask, vis, baseline, disparity, focal, pseudo, alpha, nd, ndd, e, xt, hx,
             H, D, dD, compute_jac):  # fmt: skip
    """MAP cost ``|z|^2 + |R^-1/2 (y - h(x- [+] L z))|^2``; ``h`` in ``hx``, and ``H`` too when ``compute_jac``."""
    _lower_mul(L, z, e)
    _measure_at(chart, xp, e, vis, baseline, disparity, focal, pseudo, alpha, nd, ndd, compute_jac, hx, H, xt, D, dD)
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
    """``out = M^T v`` (``M (m, n)``)."""
    np.dot(M.T, v, out)  # BLAS gemv


@njit(**_JIT)
def _posterior_covariance(L, LA, out, X):
    """``out = L A^-1 L^T`` with ``A = LA LA^T``: ``X = LA^-1 L^T`` (forward substitution by rows), ``out = X^T X``
    (BLAS, lower triangle mirrored: exactly symmetric).

    Past ``SOLVE_BLOCK`` rows the substitution is blocked: a block of rows first takes off the
    contribution of the rows solved before it in one BLAS product (``LA[blk, :i0] X[:i0]``), then
    solves its own triangle row by row; the flops of a large ``n`` run in BLAS, not in this loop.
    """
    n = L.shape[0]
    nb = SOLVE_BLOCK
    Xblk = np.empty((min(nb, n), n))
    for i0 in range(0, n, nb):
        i1 = min(i0 + nb, n)
        for i in range(i0, i1):
            for j in range(n):
                X[i, j] = L[j, i]
        if i0 > 0:
            Lb = np.empty((i1 - i0, i0))
            Xb = Xblk[: i1 - i0]
            for i in range(i0, i1):
                for k in range(i0):
                    Lb[i - i0, k] = LA[i, k]
            np.dot(Lb, X[:i0], Xb)  # BLAS gemm
            for i in range(i0, i1):
                for j in range(n):
                    X[i, j] -= Xb[i - i0, j]
        for i in range(i0, i1):
            _combine(X[i], 0, n, X, LA[i], i0, i, -1.0)
            d = LA[i, i]
            for j in range(n):
                X[i, j] /= d
    _gram_lower(X, out)  # X^T X (BLAS)
    _mirror_lower(out)


@njit(**_JIT)
def _lower_mul(L, z, out):
    """``out = L z`` (``L`` lower triangular)."""
    for i in range(L.shape[0]):
        out[i] = _dot_row(L, i, z, 0, i + 1)


@njit(**_JIT)
def iekf_update_batch(x, P, y, R, mask, vis, baseline, disparity, focal, pseudo, alpha, nd, ndd, cols, chart,
                      tol, max_iter, control, stopping, max_halvings):  # fmt: skip
    """Gauss-Newton IEKF in whitened coordinates ``x = x- [+] L z`` (``kalman.iekf_update``), per trial.

    ``chart`` as in ``ekf_update_batch`` (1: the iterates are ``aligned.chart(x-, L z)``, ``P`` that
    of the aligned error state, as ``mekf.update``; 2: ``errorstate.chart(x-, L z)``, the
    attitude error state's); ``control``: 0 none, 1 line search, 2 Levenberg-Marquardt (``lam``
    from 1e-3, /10 after an accepted step, x10 after a rejected one, as ``kalman.iekf_update``);
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
    rw = np.empty(m)
    A = np.empty((n, n))
    Afin = np.empty((n, n))
    LA = np.empty((n, n))
    Ad = np.empty((n, n) if control == 2 else (0, 0))  # Levenberg-Marquardt's damped A + lam I
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
        _whiten(hx, Hval, cols, yb, rws, Laug, Hw, rw, A)
        _mul_t(Hw, rw, g)
        for r in range(m):
            nu[b, r] = yb[r] - hx[r]
        # NIS by Woodbury: |rw|^2 - g^T A^-1 g, g = Hw^T rw
        if not _cholesky(A, LA):
            ok[b] = False
            continue
        c0 = 0.0
        for r in range(m):
            c0 += rw[r] * rw[r]
        for i in range(n):
            d[i] = g[i]
        _chol_solve(LA, d)
        nis[b] = c0 - _dot(g, d, 0, n)
        cost = c0
        for i in range(n):
            z[i] = 0.0
        _keep_linearization(A, Afin)
        failed = False
        fresh = True
        lam = 1e-3  # Levenberg-Marquardt's damping, per trial
        for it in range(max_iter):
            # z_GN = A^-1 Hw^T (rw + Hw z) = A^-1 (g + (A - I) z); from the prior (z = 0) that is d = A^-1 g of
            # the NIS above. Levenberg-Marquardt: ((1 + lam) I + Hw^T Hw) z = Hw^T (rw + Hw z_j) + lam z_j, i.e.
            # (A + lam I) z = g + (A - I) z_j + lam z_j, kept if the MAP cost does not increase (lam / 10), else x 10
            if it == 0 and control != 2:
                for i in range(n):
                    zn[i] = d[i]
            else:
                for i in range(n):
                    zn[i] = (g[i] - z[i]) + _dot_row(A, i, z, 0, n)
                M = A
                if control == 2:
                    for i in range(n):
                        zn[i] += lam * z[i]
                        for j in range(i + 1):
                            Ad[i, j] = A[i, j]
                        Ad[i, i] += lam
                    M = Ad
                if not _cholesky(M, LA):
                    failed = True
                    break
                _chol_solve(LA, zn)
            fresh = True  # LA is the factor of this iterate's A
            accepted = True
            c_new = cost
            have_jac = False  # hx, Hval already hold h and H at the accepted iterate
            if control == 1:  # backtracking line search on the MAP cost
                for i in range(n):
                    d[i] = zn[i] - z[i]
                # The full step's Mahalanobis size, known before its cost: if the full step is taken it will not
                # stop the iterations, so its cost evaluation computes H too, which the next linearization needs
                # (h and H at the same point: the same numbers as measuring again there).
                jac_full = False
                if stopping == 0 and it < max_iter - 1:
                    sf = 0.0
                    for i in range(n):
                        sf += d[i] * _dot_row(A, i, d, 0, n)
                    jac_full = not (math.sqrt(max(sf, 0.0)) < tol)
                a = 1.0
                accepted = False
                for _h in range(max_halvings + 1):
                    for i in range(n):
                        zt[i] = z[i] + a * d[i]
                    jac = jac_full and _h == 0
                    ct = _cost_at(chart, zt, xp, L, yb, rws, mk, vis, baseline, disparity, focal, pseudo, alpha[b], nd,
                                  ndd, e, xt, hx, Hval if jac else Hdummy, D, dD, jac)  # fmt: skip
                    if math.isfinite(ct) and ct <= cost:
                        accepted = True
                        have_jac = jac
                        c_new = ct
                        for i in range(n):
                            zn[i] = zt[i]
                        break
                    a *= 0.5
                if not accepted:
                    for i in range(n):
                        zn[i] = z[i]
            elif control == 2:  # Levenberg-Marquardt: the damped step, kept if the MAP cost does not increase
                fresh = False  # LA is the factor of A + lam I
                ct = _cost_at(chart, zn, xp, L, yb, rws, mk, vis, baseline, disparity, focal, pseudo, alpha[b], nd, ndd,
                              e, xt, hx, Hdummy, D, dD, False)  # fmt: skip
                accepted = math.isfinite(ct) and ct <= cost
                if accepted:
                    c_new = ct
                    lam = lam / 10.0
                else:
                    for i in range(n):
                        zn[i] = z[i]
                    lam = lam * 10.0
            its[b] += 1
            # size of the increment dz = zn - z
            size = 0.0
            if stopping == 0:  # |dz|^2 + |Hw dz|^2 = dz^T A dz
                for i in range(n):
                    dx[i] = zn[i] - z[i]
                for i in range(n):
                    size += dx[i] * _dot_row(A, i, dx, 0, n)
                size = math.sqrt(max(size, 0.0))
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
            if not have_jac:
                _lower_mul(L, z, e)
                _measure_at(chart, xp, e, vis, baseline, disparity, focal, pseudo, alpha[b], nd, ndd, True, hx, Hval,
                            xt, D, dD)  # fmt: skip
            _masked(hx, Hval, yb, mk)
            _whiten(hx, Hval, cols, yb, rws, Laug, Hw, rw, A)
            _mul_t(Hw, rw, g)
        if failed or not (fresh or _cholesky(Afin, LA)):
            ok[b] = False
            continue
        _lower_mul(L, z, e)
        _reset(chart, xp, e, xo[b])
        # P+ = L A^-1 L^T = M M^T, M = L LA^-T: the Joseph form (I - K H) P- (I - K H)^T + K R K^T
        # of kalman.iekf_update with its optimal gain K = L A^-1 Hw^T R^-1/2 at the same H
        _posterior_covariance(L, LA, Po[b], T)
    return xo, Po, nu, nis, its, conv, ok
