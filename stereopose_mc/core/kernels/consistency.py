"""Compiled (Numba) NEES of an aligned-chart estimate: the twin of ``core.aligned.nees_report``.

Per trial, from the estimate ``x_hat``, the covariance ``P`` of its aligned error state and
the truth ``x_true`` (docs/filters.md, Consistency):

- ``e = local_aligned(x_hat, x_true)``; full NEES ``e^T P^-1 e`` (``n - 1`` dof);
- gauge-projected NEES: that of ``W e`` with ``W P W^T`` for any full-rank ``W`` with ``W G = 0``,
  ``G`` the gauge direction "the same ``e_P`` for every point" (3 columns), e.g.
  ``core.aligned.gauge_complement``'s ``V^T``: ``e^T (P^-1 - P^-1 G (G^T P^-1 G)^-1 G^T P^-1) e``,
  evaluated from the full NEES's Cholesky factor ``L`` as ``|w - Q Q^T w|^2``, ``w = L^-1 e``,
  ``Q`` an orthonormal basis of ``L^-1 G`` (no second factorization, no cancellation);
- the block NEES of the attitude-chart error ``eps = local_attitude(x_true, x_hat)`` with the
  blocks of ``M P M^T``, ``M = T_attitude S_aligned`` at ``x_hat``, written out:
  ``d rho = e_c - D mean(e_P)``, ``d rho_dot = e_cdot + [v x] e_omega - [omega x] D mean(e_P)``
  (``v = D P_bar``), ``a = D delta``, ``d P_i = e_Pi + [P_i x] delta``, identity on ``omega``
  and ``k``.

``M`` is held by rows of non-zeros (``1 + 3N`` at most); the rho and rho_dot rows, whose ``3N``
point entries repeat 3 coefficients, take the point rows of ``P`` summed once instead; the
block covariances are solved by the Cholesky factorizations of ``core.kernels.cholesky``. A trial whose covariance
is not positive definite (or whose state is not finite) gets NaN for every NEES and ``pd = False``: the engine's
positive-definiteness check of ``P+`` (``mc.trial``) reads it instead of factorizing again.

A full-state filter's covariance ``P`` is not mapped (``_one_full``): the NEES with ``T P T^T``
(``T = aligned.error_map(x_hat)``) is the least ``P``-Mahalanobis norm of an ``x``-space error
that ``T`` maps to ``e``, from ``P``'s own Cholesky factor (which gives ``pd`` too), and the
attitude chart's blocks are ``P``'s own (``M T = errorstate.error_map``). Where ``P`` does not
factorize, it is mapped as ``T (T P)^T`` from the non-zeros of ``T`` (``aligned._apply_error_map``,
``_map_full``) and the NEES is that of the map, as in the numpy path. An attitude error state's
covariance is not mapped either (``_one_att``): with ``M = T_attitude S_aligned`` (whose inverse
maps it to the aligned chart), the NEES is ``|L^-1 M e|^2`` from ``P``'s own factor, and the
blocks are ``P``'s own; where ``P`` does not factorize, it is mapped to the aligned chart.

``errors_batch`` (``errors``) is the twin of ``mc.trial.errors``: the six errors the engine
records at every step, without numpy's per-call cost on small arrays.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from ..layout import (E_OMEGA, E_POINTS, E_RHO, E_RHO_DOT, E_ROT, E_SHIFT, K_SIZE, OMEGA, POINTS, QUAT, RHO,
                      RHO_DOT, VEC)  # fmt: skip
from . import attitude as _att
from . import writable as _writable
from ._refs import borrow, keep
from .aligned import _apply_error_map, _error_map, _local, _qmul
from .centred import _center_rows
from .cholesky import _cholesky, _cholesky_small, _cholesky_upper, _forward, _upper_rows
from .model import Q_END
from .model import n_points as _n_points
from .rows import _dot, _dot_row, _dot_rows, _mirror_lower

N_AXES = E_POINTS + K_SIZE  # the per-axis rows: rho, rho_dot, omega, attitude (the error state's first 12) and k

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")

KEYS = ("nees", "nees_gauge", "nees_rho", "nees_rho_dot", "nees_omega", "nees_attitude", "nees_feature_points",
        "nees_k")  # fmt: skip


@njit(**_JIT)
def _axis_row(r, ne):
    """The error state's row of per-axis row ``r`` (``N_AXES``): the first 12 as they are, then ``k``, last of ``ne``."""
    return r if r < E_POINTS else ne - K_SIZE + (r - E_POINTS)


@njit(**_JIT)
def _mahalanobis(e, P, L, w):
    """``e^T P^-1 e`` by Cholesky (``L``, ``w`` scratch; a small block's); NaN if ``P`` is not positive definite.

    A 2 x 2 or 3 x 3 block (``_mahalanobis_small``) is written out in scalars, with the same
    operations in the same order as ``_cholesky_small`` and ``_forward``: the same bits.
    """
    if P.shape[0] == 2 or P.shape[0] == 3:
        return _mahalanobis_small(e, 0, P, 0, P.shape[0])
    if not _cholesky_small(P, L):
        return np.nan
    _forward(L, e, w)
    s = 0.0
    for i in range(e.shape[0]):
        s += w[i] * w[i]
    return s


ROWS_MAX = 24  # _mahalanobis_lapack: the written-out factorization up to this size (potrf is faster past it)


@njit(**_JIT)
def _mahalanobis_lapack(e, P, L, w):
    """``_mahalanobis`` of the points' block (3N x 3N): up to ``ROWS_MAX`` rows by ``_upper_rows`` (written out, four
    rows per pass: faster than ``potrf`` on small blocks), past it by LAPACK's ``potrf``
    (``_cholesky``); NaN if ``P`` is not positive definite."""
    n = e.shape[0]
    if n > ROWS_MAX:
        if not _cholesky(P, L):
            return np.nan
        _forward(L, e, w)
        return _dot(w, w, 0, n)
    if not _upper_rows(P, L):
        return np.nan
    # w = U^-T e by rows of U: w_k = e_k / U_kk, then e_i -= U_ki w_k (i > k; each e_i's subtractions in order of k)
    for i in range(n):
        w[i] = e[i]
    for k in range(n):
        wk = w[k] / L[k, k]
        w[k] = wk
        for i in range(k + 1, n):
            w[i] -= L[k, i] * wk
    return _dot(w, w, 0, n)


@njit(**_JIT)
def _mahalanobis_small(e, o, P, r, m):
    """``_mahalanobis`` of ``e[o:o+m]`` with the block ``P[r:r+m, r:r+m]`` (``m`` 2 or 3), read in place (no views:
    each costs an atomic increment and decrement of a reference count), in scalars: ``U = L^T`` row by row
    (``_cholesky_small``: the pivot row minus the rows above, each divided by the square root of its pivot), then
    ``w = L^-1 e``."""
    three = m == 3
    d = P[r, r]
    if not d > 0.0:
        return np.nan
    d = math.sqrt(d)
    u00, u01 = P[r, r] / d, P[r + 1, r] / d
    u02 = P[r + 2, r] / d if three else 0.0
    u11 = P[r + 1, r + 1] + (-u01) * u01
    u12 = P[r + 2, r + 1] + (-u01) * u02 if three else 0.0
    d = u11
    if not d > 0.0:
        return np.nan
    d = math.sqrt(d)
    u11, u12 = u11 / d, u12 / d
    w0 = e[o] / u00
    w1 = (e[o + 1] - u01 * w0) / u11
    s = 0.0
    s += w0 * w0
    s += w1 * w1
    if three:
        u22 = P[r + 2, r + 2] + (-u02) * u02
        u22 = u22 + (-u12) * u12
        d = u22
        if not d > 0.0:
            return np.nan
        u22 = u22 / math.sqrt(d)
        t = e[o + 2] - u02 * w0
        t -= u12 * w1
        w2 = t / u22
        s += w2 * w2
    return s


@njit(**_JIT)
def _block(cnt, cols, vals, lo, hi, P, Y, C, c0, c1):
    """``C = M[lo:hi] P M[lo:hi]^T`` for the sparse rows of ``M`` (row ``r``: ``cnt[r]`` pairs ``cols, vals``).

    ``Y = M[lo:hi] P`` row by row from the non-zeros, then ``C[a, b] = Y[a] . M[lo + b]``. ``Y``
    only on the columns ``c0:c1``, which hold every non-zero of the rows (the others are not read).
    """
    m = hi - lo
    for a in range(m):
        r = lo + a
        for c in range(c0, c1):
            Y[a, c] = 0.0
        for j in range(cnt[r]):
            v = vals[r, j]
            k = cols[r, j]
            for c in range(c0, c1):
                Y[a, c] += v * P[k, c]
    _times_rows_t(cnt, cols, vals, lo, hi, Y, C)


@njit(**_JIT)
def _times_rows_t(cnt, cols, vals, lo, hi, Y, C):
    """``C = Y M[lo:hi]^T``, symmetric: ``C[a, b] = Y[a] . M[lo + b]`` from the non-zeros of ``M``'s rows."""
    for a in range(hi - lo):
        for b in range(a + 1):
            r = lo + b
            s = 0.0
            for j in range(cnt[r]):
                s += Y[a, cols[r, j]] * vals[r, j]
            C[a, b] = s
            C[b, a] = s


@njit(**_JIT)
def _block_points(cnt, cols, vals, lo, hi, P, Y, C, Sp, Wp, N, c0, c1):
    """``_block`` for rows whose point columns all carry the same 3 coefficients ``Wp[r - lo]`` (rho, rho_dot).

    ``Y[a] = (the row's other non-zeros) P + Wp[a] . Sp``, ``Sp[c] = sum_i P[12 + 3 i + c]`` (the
    point rows of ``P`` summed once per trial): 3 terms per row instead of ``3N``; on the columns ``c0:c1``.
    """
    p0, p1 = E_POINTS, E_POINTS + VEC * N
    for a in range(hi - lo):
        r = lo + a
        for c in range(c0, c1):
            Y[a, c] = Wp[a, 0] * Sp[0, c] + Wp[a, 1] * Sp[1, c] + Wp[a, 2] * Sp[2, c]
        for j in range(cnt[r]):
            k = cols[r, j]
            if k < p0 or k >= p1:
                v = vals[r, j]
                for c in range(c0, c1):
                    Y[a, c] += v * P[k, c]
    _times_rows_t(cnt, cols, vals, lo, hi, Y, C)


@njit(**_JIT)
def _point_block(xh, N, P, Y, C):
    """``_block`` of the points' rows of ``M`` (``_attitude_rows``: ``d P_i = e_Pi + [P_i x] delta``, the row of point
    ``i``'s axis ``a`` is 1 at ``e_Pi``'s column ``a``, then the two entries of ``[P_i x]`` on ``delta``) from the
    points ``P_i`` of ``x_hat`` themselves, not from the rows' list of non-zeros: the same sums in the same order,
    bit for bit (``_block`` adds each non-zero's term to ``0``, in the rows' order), without the list's indirection.
    ``Y = M_pts P`` on the columns ``delta`` and the points (those of the non-zeros), ``C = Y M_pts^T``."""
    m = VEC * N
    d0, d1, d2 = E_ROT, E_ROT + 1, E_ROT + 2
    c1 = E_POINTS + m
    for a in range(m):
        o = POINTS + a - a % 3  # the point's coordinates in x_hat
        q0, q1, q2 = xh[o], xh[o + 1], xh[o + 2]
        # [P x]'s row a % 3: (d1, -q2), (d2, q1) / (d0, q2), (d2, -q0) / (d0, -q1), (d1, q0), as _put_cross puts them
        if a % 3 == 0:
            k1, v1, k2, v2 = d1, -q2, d2, q1
        elif a % 3 == 1:
            k1, v1, k2, v2 = d0, q2, d2, -q0
        else:
            k1, v1, k2, v2 = d0, -q1, d1, q0
        k0 = E_POINTS + a
        for c in range(E_ROT, c1):
            Y[a, c] = ((0.0 + P[k0, c]) + v1 * P[k1, c]) + v2 * P[k2, c]  # (1.0 * x is x)
    for a in range(m):
        y0, y1, y2 = Y[a, d0], Y[a, d1], Y[a, d2]
        for b in range(a + 1):
            o = POINTS + b - b % 3
            if b % 3 == 0:
                s = ((0.0 + Y[a, E_POINTS + b]) + y1 * -xh[o + 2]) + y2 * xh[o + 1]
            elif b % 3 == 1:
                s = ((0.0 + Y[a, E_POINTS + b]) + y0 * xh[o + 2]) + y2 * -xh[o]
            else:
                s = ((0.0 + Y[a, E_POINTS + b]) + y0 * -xh[o + 1]) + y1 * xh[o]
            C[a, b] = s
            C[b, a] = s


@njit(**_JIT)
def _put(cnt, cols, vals, r, c, v):
    """Append the non-zero ``M[r, c] = v``."""
    j = cnt[r]
    cols[r, j] = c
    vals[r, j] = v
    cnt[r] = j + 1


@njit(**_JIT)
def _put_cross(cnt, cols, vals, r, c, v):
    """Append the non-zeros of the block ``M[r:r+3, c:c+3] = [v x]`` (the cross-product matrix), row by row."""
    _put(cnt, cols, vals, r, c + 1, -v[2])
    _put(cnt, cols, vals, r, c + 2, v[1])
    _put(cnt, cols, vals, r + 1, c, v[2])
    _put(cnt, cols, vals, r + 1, c + 2, -v[0])
    _put(cnt, cols, vals, r + 2, c, -v[1])
    _put(cnt, cols, vals, r + 2, c + 1, v[0])


@njit(**_JIT)
def _forward_r(R, b, out):
    """``out = L^-1 b`` for ``P = L L^T`` given as its square root ``R = J L^T`` (``P = R^T R``: the rows of the upper
    factor ``L^T`` in reverse order, as the compiled update gives them): forward substitution, ``L[i, k] = R[n - 1 -
    k, i]`` (by rows of ``L``: one running sum per row, the columns of ``R`` read with their stride)."""
    n = R.shape[0]
    for i in range(n):
        t = b[i]
        for k in range(i):
            t -= R[n - 1 - k, i] * out[k]
        out[i] = t / R[n - 1 - i, i]


@njit(**_JIT)
def _gauge_forward(R, U, N, centred):
    """``U[j] = L^-1 G_j`` for the 3 gauge columns at once (``G_j``: 1 on every point's row ``12 + 3 i + j``), ``L``
    given by ``R`` as in ``_forward_r``; ``centred``: ``L`` the factor of the centred covariance ``T P T^T``
    (``core.kernels.centred``), where the gauge columns are ``T G_j``, the unit vectors of the points' mean
    (row ``12 + j``: the deviations of a common shift are zero).

    ``G``, hence ``U``, is zero above the points' rows (12): forward substitution from there,
    the three right-hand sides in one pass over ``L`` (three independent sums per row).
    """
    ne = R.shape[0]
    for j in range(3):
        for i in range(E_POINTS):
            U[j, i] = 0.0
    for i in range(E_POINTS, ne):
        j = (i - E_POINTS) % VEC
        p = i < E_POINTS + VEC * (1 if centred else N)  # a row where G_j (T G_j) is 1, for j = (i - E_POINTS) % VEC
        s0 = 1.0 if p and j == 0 else 0.0
        s1 = 1.0 if p and j == 1 else 0.0
        s2 = 1.0 if p and j == 2 else 0.0
        for k in range(E_POINTS, i):
            c = R[ne - 1 - k, i]
            s0 -= c * U[0, k]
            s1 -= c * U[1, k]
            s2 -= c * U[2, k]
        r = 1.0 / R[ne - 1 - i, i]  # (one division per row, not three)
        U[0, i] = s0 * r
        U[1, i] = s1 * r
        U[2, i] = s2 * r


@njit(**_JIT)
def _estimation_error(xh, xt, nh, nt, eps, tmp, dq):
    """The attitude-chart error anchored at the truth, ``x_hat = x_true [+] eps`` (``errorstate.estimation_error``;
    ``nh, nt``: the quaternions' norms)."""
    ne = eps.shape[0]
    for r in range(E_ROT):
        eps[r] = xh[r] - xt[r]
    for r in range(E_POINTS, ne):
        eps[r] = xh[r + E_SHIFT] - xt[r + E_SHIFT]
    q = QUAT
    tmp[0], tmp[1], tmp[2], tmp[3] = xt[q] / nt, -xt[q + 1] / nt, -xt[q + 2] / nt, -xt[q + 3] / nt
    _qmul(xh[QUAT:Q_END], tmp, dq)
    for j in range(3):
        eps[E_ROT + j] = 2.0 * (dq[1 + j] / nh) / (dq[0] / nh)


@njit(**_JIT)
def _attitude_rows(xh, N, D, vh, cnt, cols, vals, Wp):
    """``M = d eps / d e`` at ``x_hat`` (rows of the attitude chart, columns of the aligned one; ``aligned``'s
    ``errorstate.error_map @ chart_jacobian``) by rows of non-zeros (``cnt``, ``cols``, ``vals``); ``D = D(q_hat)``
    and ``vh = D P_bar_hat`` from ``_local``; ``Wp`` gets the point columns' coefficients of the rho and rho_dot
    rows (``_block_points``)."""
    ne = cnt.shape[0]
    wh = xh[OMEGA : OMEGA + VEC]
    for r in range(ne):
        cnt[r] = 0
    # (rows: the attitude chart's eps, columns: the aligned chart's e; the same offsets E_*)
    for r in range(3):
        _put(cnt, cols, vals, E_RHO + r, E_RHO + r, 1.0)  # d rho / d e_c
        _put(cnt, cols, vals, E_RHO_DOT + r, E_RHO_DOT + r, 1.0)  # d rho_dot / d e_cdot
        _put(cnt, cols, vals, E_OMEGA + r, E_OMEGA + r, 1.0)
        for c in range(3):
            _put(cnt, cols, vals, E_ROT + r, E_ROT + c, D[r, c])  # a = D delta
    # [v x] on e_omega in rho_dot
    _put_cross(cnt, cols, vals, E_RHO_DOT, E_OMEGA, vh)
    for r in range(3):
        for c in range(3):
            Wp[r, c] = -D[r, c] / N
            # [omega x] D
            Wp[3 + r, c] = -(wh[(r + 1) % 3] * D[(r + 2) % 3, c] - wh[(r + 2) % 3] * D[(r + 1) % 3, c]) / N
    for i in range(N):
        p = xh[POINTS + VEC * i : POINTS + VEC * (i + 1)]
        for r in range(3):
            for c in range(3):
                _put(cnt, cols, vals, E_RHO + r, E_POINTS + VEC * i + c, Wp[r, c])
                _put(cnt, cols, vals, E_RHO_DOT + r, E_POINTS + VEC * i + c, Wp[3 + r, c])
            _put(cnt, cols, vals, E_POINTS + VEC * i + r, E_POINTS + VEC * i + r, 1.0)
        # [P_i x] on delta
        _put_cross(cnt, cols, vals, E_POINTS + VEC * i, E_ROT, p)
    for j in range(ne - K_SIZE, ne):
        _put(cnt, cols, vals, j, j, 1.0)


@njit(**_JIT)
def _point_rows_sum(P, N, Sp):
    """``Sp[c] = sum_i P[12 + 3 i + c]`` (``(3, n-1)``): the point rows of ``P`` summed (``_block_points``)."""
    ne = Sp.shape[1]
    for c in range(ne):
        Sp[0, c] = 0.0
        Sp[1, c] = 0.0
        Sp[2, c] = 0.0
    for i in range(N):
        for a in range(3):
            for c in range(ne):
                Sp[a, c] += P[E_POINTS + VEC * i + a, c]


@njit(**_JIT)
def _one(xh, P, xt, N, out, e, eps, cnt, cols, vals, C, Rc, Lb, w, U, u, Y, D, Dt, R, dq, tmp, v3, Sp, Wp, Uf, given,
         var, centred):
    """The 8 NEES of one aligned-chart covariance ``P`` into ``out`` (module docstring); False if ``P`` is not
    positive definite (nothing written). ``Rc``: ``P``'s square root where ``given``, else ``_own_root``'s output
    (``Uf`` scratch); ``centred`` (given): ``Rc`` is the square root ``J M^T`` of the centred covariance ``T P T^T =
    M M^T`` (``core.kernels.centred``, the compiled update's large states), and the full and gauge NEES are those of
    ``T e`` with it (``e^T P^-1 e = (T e)^T (T P T^T)^-1 T e``; the gauge columns ``T G``). Also leaves the
    attitude-chart error ``eps`` and, in ``var (N_AXES,)``, the variances of its per-axis rows (the diagonals of the
    blocks ``M P M^T`` formed for the block NEES: ``axes.axis_errors_batch``'s numbers, bit for bit), which the
    compiled update returns beside the NEES."""
    n = xh.shape[0]
    ne = n - 1
    # --- aligned error at the estimate: e = local_aligned(x_hat, x_true); D, v_hat = v3[2] kept for M below
    nh, nt = _local(xh, xt, e, D, Dt, R, dq, tmp, v3)
    # --- full NEES: |w|^2, w = L^-1 e, P = L L^T (one factorization serves the gauge NEES too), given as
    # ``Rc = J L^T`` (``given``: the compiled update's), or factorized here (``_own_root``, ``Uf`` scratch)
    if not (given or _own_root(P, Uf, Rc)):
        return False
    if centred:  # T e (into u, free until the blocks below), then |M^-1 T e|^2
        _center_rows(e.reshape((ne, 1)), u.reshape((ne, 1)), N)
        _forward_r(Rc, u, w)
    else:
        _forward_r(Rc, e, w)
    out[0] = _dot(w, w, 0, ne)
    # --- gauge-projected NEES: e^T (P^-1 - P^-1 G (G^T P^-1 G)^-1 G^T P^-1) e, G = "the same e_P for every
    # point" (3 columns), the NEES of W e with W P W^T for any W with W G = 0 of full rank (W V^T = I on
    # the complement: core.aligned.gauge_complement); as |w - Q Q^T w|^2, Q an orthonormal basis of U = L^-1 G
    # (modified Gram-Schmidt), with no cancellation between the full NEES and the gauge part.
    _gauge_forward(Rc, U, N, centred)
    for j in range(3):
        for k in range(j):
            s = _dot_rows(U, k, U, j, E_POINTS, ne)
            for i in range(E_POINTS, ne):
                U[j, i] -= s * U[k, i]
        s = math.sqrt(_dot_rows(U, j, U, j, E_POINTS, ne))
        for i in range(E_POINTS, ne):
            U[j, i] /= s
    for j in range(3):
        s = _dot_row(U, j, w, E_POINTS, ne)
        for i in range(E_POINTS, ne):
            w[i] -= s * U[j, i]
    out[1] = _dot(w, w, 0, ne)
    _estimation_error(xh, xt, nh, nt, eps, tmp, dq)
    _attitude_rows(xh, N, D, v3[2], cnt, cols, vals, Wp)
    _point_rows_sum(P, N, Sp)
    for b in range(6):
        p1 = E_POINTS + VEC * N
        lo = (E_RHO, E_RHO_DOT, E_OMEGA, E_ROT, E_POINTS, p1)[b]
        hi = (E_RHO_DOT, E_OMEGA, E_ROT, E_POINTS, p1, ne)[b]
        # the columns of the block's non-zeros: rho (and rho_dot, omega) and the points; omega; delta; delta and
        # the points; k
        c0 = (E_RHO, E_RHO_DOT, E_OMEGA, E_ROT, E_ROT, p1)[b]
        c1 = (p1, p1, E_ROT, E_POINTS, p1, ne)[b]
        m = hi - lo
        if b < 2:
            _block_points(cnt, cols, vals, lo, hi, P, Y, C, Sp, Wp[3 * b : 3 * b + 3], N, c0, c1)
        elif b == 4:  # the points' block, from the points themselves (_block's numbers)
            _point_block(xh, N, P, Y, C)
        else:
            _block(cnt, cols, vals, lo, hi, P, Y, C, c0, c1)
        if b != 4:  # the per-axis variances (``axes.axis_errors_batch``'s, the same blocks): all but the points'
            at = lo if b < 4 else E_POINTS
            for a in range(m):
                var[at + a] = C[a, a]
        out[2 + b] = _mahalanobis(eps[lo:hi], C[:m, :m], Lb[:m, :m], u)
    return True


@njit(**_JIT)
def _preimage(Tm, e, dx, N):
    """``dx (n)`` with ``T dx = e`` (``T = aligned.error_map(x)``, ``_error_map``'s ``Tm``) and its quaternion part
    orthogonal to ``q`` (``T``'s null direction), from ``T``'s block structure: the rows of ``omega``, ``k`` and
    the points are identity rows (the points' plus the quaternion's columns), those of ``delta`` are
    ``Xi = 2 [L(q^*)]_vec`` on the quaternion (``Xi Xi^T = 4 I``, ``Xi q = 0``: ``dq = Xi^T delta / 4``), and
    those of ``rho`` and ``rho_dot`` are identity rows plus columns solved before them."""
    ne, n = Tm.shape
    for c in range(n):
        dx[c] = 0.0
    for a in range(3):
        dx[OMEGA + a] = e[E_OMEGA + a]
    d, q = E_ROT, QUAT
    for j in range(4):
        dx[q + j] = 0.25 * (Tm[d, q + j] * e[d] + Tm[d + 1, q + j] * e[d + 1] + Tm[d + 2, q + j] * e[d + 2])
    for j in range(K_SIZE):
        dx[n - K_SIZE + j] = e[ne - K_SIZE + j]
    for r in range(E_POINTS, E_POINTS + VEC * N):
        dx[r + E_SHIFT] = e[r] - (Tm[r, q] * dx[q] + Tm[r, q + 1] * dx[q + 1] + Tm[r, q + 2] * dx[q + 2]
                                  + Tm[r, q + 3] * dx[q + 3])  # fmt: skip
    for r in range(E_OMEGA):  # rho, rho_dot: their own column r (dx[r], still 0, adds nothing); the others solved before
        dx[r] = e[r] - _dot_row(Tm, r, dx, 0, n)


@njit(**_JIT)
def _forward5(R, W):
    """``W[j] <- L^-1 W[j]`` for the 5 rows of ``W`` in one pass over ``L`` (``P = L L^T`` given by ``R``, as in
    ``_forward_r``): five running sums per row of ``L``, each entry read once."""
    n = R.shape[0]
    for i in range(n):
        s0, s1, s2, s3, s4 = W[0, i], W[1, i], W[2, i], W[3, i], W[4, i]
        for k in range(i):
            c = R[n - 1 - k, i]
            s0 -= c * W[0, k]
            s1 -= c * W[1, k]
            s2 -= c * W[2, k]
            s3 -= c * W[3, k]
            s4 -= c * W[4, k]
        r = 1.0 / R[n - 1 - i, i]  # (one division per row, not five)
        W[0, i], W[1, i], W[2, i], W[3, i], W[4, i] = s0 * r, s1 * r, s2 * r, s3 * r, s4 * r


@njit(**_JIT)
def _project_off(W, j0, j1):
    """Rows ``j0..j1-1`` of ``W`` made orthonormal (modified Gram-Schmidt, in order) and ``W[0]`` projected off
    each in turn; returns ``|W[0]|^2`` after the first projection (the others are in ``W[0]``). Each dot product
    in four partial sums (``rows._dot_row``: one running sum is a chain of dependent additions)."""
    n = W.shape[1]
    first = 0.0
    for j in range(j0, j1):
        for k in range(j0, j):
            s = _dot_rows(W, k, W, j, 0, n)
            for i in range(n):
                W[j, i] -= s * W[k, i]
        s = 1.0 / math.sqrt(_dot_rows(W, j, W, j, 0, n))
        for i in range(n):
            W[j, i] *= s
        c = _dot_rows(W, j, W, 0, 0, n)
        for i in range(n):
            W[0, i] -= c * W[j, i]
        if j == j0:
            first = _dot_rows(W, 0, W, 0, 0, n)
    return first


@njit(**_JIT)
def _one_full(xh, P, Rp, xt, N, out, Tm, e, W, eps, C, Lb, w, D, Dt, R, dq, tmp, v3):
    """``_one`` for a full-state covariance ``P = Lp Lp^T`` (its own Cholesky factor, given as ``Rp = J Lp^T``:
    ``_forward_r``), without mapping ``P``.

    ``T = aligned.error_map(x_hat)`` has full row rank and ``T t = 0``, ``t = (0, q/|q|, 0)``, so
    the NEES of ``e`` with ``T P T^T`` is the least ``P``-Mahalanobis norm of an ``x``-space
    error that ``T`` maps to ``e``: ``min_s |Lp^-1 (dx + s t)|^2`` for any ``dx`` with ``T dx = e``
    (``_preimage``), i.e. ``|u|^2`` of ``u = Lp^-1 dx`` projected off ``Lp^-1 t``. The gauge-projected
    NEES projects off the preimages of the 3 gauge columns too (``d P_i = e_j`` for every point,
    ``d rho`` and ``d rho_dot`` minus the sums of ``T``'s point columns; modified Gram-Schmidt, as
    ``_one``: no cancellation between the full NEES and the gauge part). The blocks of the
    attitude chart's covariance ``M T P T^T M^T`` are those of ``T_att P T_att^T`` (``M T = T_att =
    errorstate.error_map(x_hat)``: identity but ``Xi_att`` on the quaternion), i.e. ``P``'s own
    diagonal blocks, and ``Xi_att P_qq Xi_att^T`` for the attitude. The same NEES as ``_one`` on
    ``_map_full``'s ``T P T^T``, to round-off, with no product of ``P``. ``W (5, n)``: scratch.
    """
    n = xh.shape[0]
    ne = n - 1
    nh, nt = _local(xh, xt, e, D, Dt, R, dq, tmp, v3)
    _error_map(xh, Tm)
    _preimage(Tm, e, W[0], N)
    for j in range(1, 5):
        for c in range(n):
            W[j, c] = 0.0
    for j in range(4):
        W[1, QUAT + j] = xh[QUAT + j] / nh  # t
    for j in range(3):  # gauge column j (W[2 + j]): d P_i = e_j for every point, rho and rho_dot compensating
        for i in range(N):
            W[2 + j, POINTS + VEC * i + j] = 1.0
        for r in range(E_OMEGA):  # e_c, e_cdot
            s = 0.0
            for i in range(N):
                s += Tm[r, POINTS + VEC * i + j]
            W[2 + j, r] = -s
    _forward5(Rp, W)
    out[0] = _project_off(W, 1, 5)
    out[1] = _dot_rows(W, 0, W, 0, 0, n)
    # --- blocks: rho, rho_dot, omega, the points and k are P's own; the attitude's is Xi_att P_qq Xi_att^T
    _estimation_error(xh, xt, nh, nt, eps, tmp, dq)
    q = QUAT
    q0, q1, q2, q3 = xh[q] / nh, xh[q + 1] / nh, xh[q + 2] / nh, xh[q + 3] / nh
    # Xi = Lb[:3, :4]: errorstate.attitude_map (attitude._error_map), 2 [R(q^*)]_vec; Y = Xi P_qq in C[3:6, :4];
    # Ca = Xi P_qq Xi^T in C[:3, :3] (indexed in place: no views, whose reference counts cost atomic operations)
    Lb[0, 0], Lb[0, 1], Lb[0, 2], Lb[0, 3] = -2.0 * q1, 2.0 * q0, -2.0 * q3, 2.0 * q2
    Lb[1, 0], Lb[1, 1], Lb[1, 2], Lb[1, 3] = -2.0 * q2, 2.0 * q3, 2.0 * q0, -2.0 * q1
    Lb[2, 0], Lb[2, 1], Lb[2, 2], Lb[2, 3] = -2.0 * q3, -2.0 * q2, 2.0 * q1, 2.0 * q0
    for a in range(3):
        for c in range(4):
            C[3 + a, c] = Lb[a, 0] * P[q, q + c] + Lb[a, 1] * P[q + 1, q + c] + Lb[a, 2] * P[q + 2, q + c] + \
                Lb[a, 3] * P[q + 3, q + c]  # fmt: skip
    for a in range(3):
        for b in range(a + 1):
            s = C[3 + a, 0] * Lb[b, 0] + C[3 + a, 1] * Lb[b, 1] + C[3 + a, 2] * Lb[b, 2] + C[3 + a, 3] * Lb[b, 3]
            C[a, b] = s
            C[b, a] = s
    p1 = E_POINTS + VEC * N
    out[2] = _mahalanobis_small(eps, E_RHO, P, RHO, VEC)
    out[3] = _mahalanobis_small(eps, E_RHO_DOT, P, RHO_DOT, VEC)
    out[4] = _mahalanobis_small(eps, E_OMEGA, P, OMEGA, VEC)
    out[5] = _mahalanobis_small(eps, E_ROT, C, 0, VEC)
    p, n1 = POINTS, p1 + E_SHIFT
    out[6] = _mahalanobis_lapack(eps[E_POINTS:p1], P[p:n1, p:n1], Lb[: 3 * N, : 3 * N], w[: 3 * N])
    out[7] = _mahalanobis_small(eps, p1, P, n1, ne - p1)  # (k: 2 x 2)


@njit(**_JIT)
def _one_att(xh, P, Rp, xt, N, out, e, eps, cnt, cols, vals, W, Lb, w, D, Dt, R, dq, tmp, v3, Wp):
    """``_one`` for an attitude error state's covariance ``P = Lp Lp^T`` (its own Cholesky factor, given as
    ``Rp = J Lp^T``: ``_forward_r``), without mapping.

    The aligned chart's covariance is ``Pa = M^-1 P M^-T`` with ``M = T_attitude S_aligned`` at
    ``x_hat`` (``_attitude_rows``; for a unit quaternion ``M^-1 = T_aligned S_attitude`` exactly,
    ``nees_batch``), so the NEES of ``e`` with ``Pa`` is ``|Lp^-1 M e|^2``; the gauge-projected one
    projects that vector off ``Lp^-1 M G`` (``G`` the 3 gauge columns; modified Gram-Schmidt, as
    ``_one``), and the attitude chart's blocks of ``M Pa M^T = P`` are ``P``'s own diagonal blocks.
    The same NEES as ``_one`` on ``M^-1 P M^-T``, to round-off, with no product of ``P``.
    ``W (5, n-1)``: scratch.
    """
    ne = xh.shape[0] - 1
    nh, nt = _local(xh, xt, e, D, Dt, R, dq, tmp, v3)
    _attitude_rows(xh, N, D, v3[2], cnt, cols, vals, Wp)
    p1 = E_POINTS + VEC * N
    # W[0] = M e; W[1 + j] = M G_j (G_j: 1 on every point's row E_POINTS + 3 i + j); W[4] unused (zero)
    for r in range(ne):
        s, g0, g1, g2 = 0.0, 0.0, 0.0, 0.0
        for k in range(cnt[r]):
            c = cols[r, k]
            v = vals[r, k]
            s += v * e[c]
            if c >= E_POINTS and c < p1:
                j = (c - E_POINTS) % VEC
                if j == 0:
                    g0 += v
                elif j == 1:
                    g1 += v
                else:
                    g2 += v
        W[0, r], W[1, r], W[2, r], W[3, r], W[4, r] = s, g0, g1, g2, 0.0
    _forward5(Rp, W)
    out[0] = _dot_rows(W, 0, W, 0, 0, ne)
    _project_off(W, 1, 4)
    out[1] = _dot_rows(W, 0, W, 0, 0, ne)
    # --- blocks: P's own (rho, rho_dot, omega, attitude, the points, k)
    _estimation_error(xh, xt, nh, nt, eps, tmp, dq)
    for k, o in enumerate((E_RHO, E_RHO_DOT, E_OMEGA, E_ROT)):
        out[2 + k] = _mahalanobis(eps[o : o + VEC], P[o : o + VEC, o : o + VEC], Lb, w)
    out[6] = _mahalanobis_lapack(eps[E_POINTS:p1], P[E_POINTS:p1, E_POINTS:p1], Lb[: 3 * N, : 3 * N], w[: 3 * N])
    out[7] = _mahalanobis(eps[p1:ne], P[p1:ne, p1:ne], Lb[: ne - p1, : ne - p1], w[: ne - p1])


@njit(**_JIT)
def _map_full(x, P, Tm, TP, Pt, Pa, Sp):
    """``Pa = T P T^T`` (lower triangle mirrored), ``T = aligned.error_map(x)``: ``TP = T P``, ``Pa = T (TP)^T``
    (``P`` symmetric) by ``_apply_error_map``, ``Pt`` the transposed scratch (``n x n-1``)."""
    N = _n_points(x.shape[0])
    _error_map(x, Tm)
    _apply_error_map(Tm, N, P, TP, Sp)
    Pt[:, :] = TP.T
    _apply_error_map(Tm, N, Pt, Pa, Sp, True)
    _mirror_lower(Pa)


@njit(**_JIT)
def errors_batch(x_hat, x_true):
    """The six errors ``(B, 6)`` of ``mc.trial.errors`` (m, m/s, deg/s, deg, -, -); ``x_true (B, n)``.

    ``|d rho|``, ``|d rho_dot|``, ``|d omega|``, the attitude error ``2 atan2(|vec q_e|, |q_e,0|)``,
    ``q_e = q_true/|q_true| (x) (q_hat/|q_hat|)^*`` (``quaternion.error_angle``) and ``|d k1|``,
    ``|d k2|``, in the order of numpy's reductions (the same numbers to the last bit or two).
    """
    B, n = x_hat.shape
    out = np.empty((B, 6))
    rad = 180.0 / math.pi
    x_hat, x_true = borrow((x_hat, x_true))  # (_refs: the caller's; no reference counts in the views below)
    for t in range(B):
        xh, xt = x_hat[t], x_true[t]
        for b, o in enumerate((RHO, RHO_DOT, OMEGA)):
            s = 0.0
            for j in range(o, o + VEC):
                d = xh[j] - xt[j]
                s += d * d
            out[t, b] = math.sqrt(s)
        out[t, 2] *= rad
        p0, p1, p2, p3 = xt[QUAT], xt[QUAT + 1], xt[QUAT + 2], xt[QUAT + 3]
        q0, q1, q2, q3 = xh[QUAT], xh[QUAT + 1], xh[QUAT + 2], xh[QUAT + 3]
        nt = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2 + p3 * p3)
        nh = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        p0, p1, p2, p3 = p0 / nt, p1 / nt, p2 / nt, p3 / nt
        q0, q1, q2, q3 = q0 / nh, -(q1 / nh), -(q2 / nh), -(q3 / nh)
        e0 = p0 * q0 - p1 * q1 - p2 * q2 - p3 * q3
        e1 = p0 * q1 + p1 * q0 + p2 * q3 - p3 * q2
        e2 = p0 * q2 - p1 * q3 + p2 * q0 + p3 * q1
        e3 = p0 * q3 + p1 * q2 - p2 * q1 + p3 * q0
        out[t, 3] = 2.0 * math.atan2(math.sqrt(e1 * e1 + e2 * e2 + e3 * e3), abs(e0)) * rad
        out[t, 4] = abs(xh[n - K_SIZE] - xt[n - K_SIZE])
        out[t, 5] = abs(xh[n - K_SIZE + 1] - xt[n - K_SIZE + 1])
    return out


def errors(x_hat: np.ndarray, x_true: np.ndarray) -> np.ndarray:
    """``mc.trial.errors`` of ``x_hat (B, n)`` against ``x_true (n,)`` or ``(B, n)`` on the compiled kernel."""
    x_hat = _writable(x_hat)
    return errors_batch(x_hat, _writable(np.broadcast_to(x_true, x_hat.shape)))


_EXPONENT = 0x7FF0000000000000  # a float64's exponent bits: all set for +-inf and NaN only


@njit(**_JIT)
def _finite(v):
    """Whether every entry of the contiguous vector ``v`` is finite: none has all its exponent bits set (its bits
    read as integers). A count of integer tests, which the compiler vectorizes without reassociating a float sum
    (twice as fast as four float sums of ``0 x v_i`` on a 30 x 30 ``P``)."""
    b = v.view(np.int64)
    c = 0
    for i in range(b.shape[0]):
        c += (b[i] & _EXPONENT) == _EXPONENT
    return c == 0


@njit(**_JIT)
def _diagonal(P):
    """Whether the square ``P`` is diagonal (its lower triangle read: a dense ``P`` answers at its first entry)."""
    n = P.shape[0]
    for i in range(1, n):
        for j in range(i):
            if P[i, j] != 0.0:
                return False
    return True


@njit(**_JIT)
def _own_root(P, U, R):
    """``R = J U``, ``U`` the upper Cholesky factor of ``P`` (``P = U^T U = R^T R``), the layout of the compiled
    update's square roots (``nees_batch``); False if ``P`` is not positive definite (``_cholesky_upper``).

    A diagonal ``P`` (the scenario's initial covariance, at step 0) is factorized without ``potrf``: ``U`` is the
    square root of its diagonal, the numbers ``potrf`` gives (``sqrt(P_jj - 0)``, ``0 / U_jj``).
    """
    n = U.shape[0]
    if _diagonal(P):
        for j in range(n):
            d = P[j, j]
            if not (d > 0.0 and d < np.inf):
                return False
        for j in range(n):
            for i in range(n):
                R[j, i] = 0.0
            R[j, n - 1 - j] = math.sqrt(P[n - 1 - j, n - 1 - j])
        return True
    if not _cholesky_upper(P, U):
        return False
    for j in range(n):
        for i in range(n):
            R[j, i] = U[n - 1 - j, i]
    return True


@njit(**_JIT)
def _factor_given(R):
    """Whether the square root ``R = J U`` (``nees_batch``'s ``Rg``) is given: the diagonal of ``U``
    (``R[n - 1 - i, i]``) is finite and positive (NaN at ``U[0, 0]`` marks a missing one)."""
    n = R.shape[0]
    for i in range(n):
        d = R[n - 1 - i, i]
        if not (d > 0.0 and d < np.inf):
            return False
    return True


@njit(**_JIT)
def _take(buf, at, c, a, b):
    """``buf[at : at + c a b]`` as ``c`` matrices ``a x b`` (C order), and the next offset."""
    return buf[at : at + c * a * b].reshape((c, a, b)), at + c * a * b


# The scratch arrays of ``_nees_one`` (``_nees_scratch``), by name: the matrices ``ne x ne`` (Mi, Pa, Lr, C, L, Lb,
# Y), ``ne x n`` (Tm, TP), ``n x ne`` (Sa, Pt), ``m x m`` (Uf, Rf: P's own upper factor and its root J U), the vectors
# of ``ne`` (e0 = 0, e, eps, w, u), the NEES blocks' sparse rows (cnt, cols, vals), 3 x 3 (D, Dt, R), 4-vectors
# (dq, tmp), 6 x 3 (v3, Wp), 3 x ne (U, Sp), 3 x n (Sm), 5 x n (W5), the per-axis variances (ax, N_AXES: _one's)
NeesScratch = namedtuple("NeesScratch", ("Tm", "Sa", "Mi", "e0", "TP", "Pt", "Sm", "Pa", "Uf", "Rf", "Lr", "e", "eps",
                                         "cnt", "cols", "vals", "C", "L", "Lb", "w", "U", "u", "Y", "D", "Dt", "R",
                                         "dq", "tmp", "v3", "Sp", "Wp", "W5", "ax"))  # fmt: skip


@njit(**_JIT)
def _nees_scratch(n, m):
    """The scratch arrays of ``_nees_one`` (a ``NeesScratch``) for a state of ``n`` and a covariance of ``m``
    columns: views into one
    float and one integer buffer (two allocations instead of 32: the update kernels make it at every call that
    evaluates NEES), grouped by shape."""
    ne = n - 1
    k = VEC + VEC * _n_points(n)
    buf = np.empty(4 * ne * n + 7 * ne * ne + 2 * m * m + 8 * n + ne * (k + 11) + 71 + N_AXES)  # the views below
    ints = np.zeros(ne + ne * k, np.int64)
    sq, at = _take(buf, 0, 7, ne, ne)  # Mi, Pa, Lr, C, L, Lb, Y
    tn, at = _take(buf, at, 2, ne, n)  # Tm, TP
    nt, at = _take(buf, at, 2, n, ne)  # Sa, Pt
    mm, at = _take(buf, at, 2, m, m)  # Uf, Rf
    vec, at = _take(buf, at, 1, 5, ne)  # e0, e, eps, w, u
    vals, at = _take(buf, at, 1, ne, k)
    d3, at = _take(buf, at, 3, 3, 3)  # D, Dt, R
    q4, at = _take(buf, at, 1, 2, 4)  # dq, tmp
    s6, at = _take(buf, at, 2, 6, 3)  # v3, Wp
    s3, at = _take(buf, at, 2, 3, ne)  # U, Sp
    sm, at = _take(buf, at, 1, 3, n)  # Sm
    w5, at = _take(buf, at, 1, 5, n)  # W5
    ax, at = _take(buf, at, 1, 1, N_AXES)  # ax
    vec[0, 0, :] = 0.0
    vals[0, :, :] = 0.0
    v, q = vec[0], q4[0]
    return NeesScratch(Tm=tn[0], Sa=nt[0], Mi=sq[0], e0=v[0], TP=tn[1], Pt=nt[1], Sm=sm[0], Pa=sq[1], Uf=mm[0],
                       Rf=mm[1], Lr=sq[2], e=v[1], eps=v[2], cnt=ints[:ne], cols=ints[ne:].reshape((ne, k)),
                       vals=vals[0], C=sq[3], L=sq[4], Lb=sq[5], w=v[3], U=s3[0], u=v[4], Y=sq[6], D=d3[0], Dt=d3[1],
                       R=d3[2], dq=q[0], tmp=q[1], v3=s6[0], Sp=s3[1], Wp=s6[1], W5=w5[0], ax=ax[0, 0])  # fmt: skip


@njit(**_JIT)
def _nees_given(xh, P, xt, Rg, out, Tm, e, W, eps, C, Lb, w, D, Dt, R, dq, tmp, v3):
    """``_nees_one`` of a full-state ``P`` with its square root ``Rg`` given (the compiled update's posteriors), with
    the 13 scratch arrays of ``_one_full`` as arguments: 1 (the NEES written, ``P`` positive definite), 0 (the state
    or ``P`` not finite: nothing written), -1 (the square root is not given: ``_nees_one``'s other paths apply).
    The update calls it on every posterior of the full state, not ``_nees_one`` with its 33-array scratch tuple: each
    array a compiled function takes costs an atomic increment and decrement of its reference count."""
    if not (_finite(xh) and _finite(xt) and _finite(P.ravel())):
        return 0
    if not _factor_given(Rg):
        return -1
    _one_full(xh, P, Rg, xt, _n_points(xh.shape[0]), out, Tm, e, W, eps, C, Lb, w, D, Dt, R, dq, tmp, v3)
    return 1


@njit(**_JIT)
def _nees_one(xh, P, xt, attitude, Rg, have, out, ws, centred):
    """One trial of ``nees_batch``: its 8 NEES into ``out`` (left as they are, NaN, where the state or ``P`` is not
    finite or ``P`` is not positive definite) and ``pd``, returned. ``Rg``: ``P``'s square root ``J U`` where the
    caller has one (``have``; used where ``_factor_given``), or with ``centred`` (an aligned-chart ``P``) the square
    root of its centred covariance ``T P T^T`` (``_one``; the compiled update's large states, which form ``P+``
    from it: no factorization of ``P+`` again); ``ws``: ``_nees_scratch``. The compiled update calls
    it on each posterior as soon as it is formed (``core.kernels.update``: ``P+`` and its square root still in cache;
    the full state's through ``_nees_given`` first, the same numbers).
    """
    Tm, Sa, Mi, e0, TP, Pt, Sm, Pa, Uf, Rf = ws.Tm, ws.Sa, ws.Mi, ws.e0, ws.TP, ws.Pt, ws.Sm, ws.Pa, ws.Uf, ws.Rf
    Lr, e, eps, cnt, cols, vals, C, L, Lb = ws.Lr, ws.e, ws.eps, ws.cnt, ws.cols, ws.vals, ws.C, ws.L, ws.Lb
    w, U, u, Y, D, Dt, R, dq, tmp = ws.w, ws.U, ws.u, ws.Y, ws.D, ws.Dt, ws.R, ws.dq, ws.tmp
    v3, Sp, Wp, W5, ax = ws.v3, ws.Sp, ws.Wp, ws.W5, ws.ax
    n = xh.shape[0]
    ne = n - 1
    N = _n_points(n)
    full = P.shape[0] == n
    mapped = full or attitude
    if not (_finite(xh) and _finite(xt) and _finite(P.ravel())):
        return False
    given = have and _factor_given(Rg)
    Rt = Rg if given else Rf  # P's square root J U (P = U^T U): given, or factorized here (_own_root)
    if full and (given or _own_root(P, Uf, Rf)):  # positive definite: the NEES from P's own factor
        _one_full(xh, P, Rt, xt, N, out, Tm, e, W5, eps, C, Lb, w, D, Dt, R, dq, tmp, v3)
        return True
    if attitude and (given or _own_root(P, Uf, Rf)):  # the same for an attitude error state's P
        _one_att(xh, P, Rt, xt, N, out, e, eps, cnt, cols, vals, W5[:, :ne], Lb, w, D, Dt, R, dq, tmp, v3, Wp)
        return True
    if mapped:  # P does not factorize: the NEES of the mapped covariance, as the numpy path (pd stays False)
        if full:
            _map_full(xh, P, Tm, TP, Pt, Pa, Sm)
        else:  # M^-1 = T_aligned S_attitude
            _error_map(xh, Tm)
            _att._chart_jacobian(xh, e0, Sa)
            np.dot(Tm, Sa, Mi)
            np.dot(Mi, P, C)
            np.dot(C, Mi.T, Pa)
            _mirror_lower(Pa)
        _one(xh, Pa, xt, N, out, e, eps, cnt, cols, vals, C, Lr, Lb, w, U, u, Y, D, Dt, R, dq, tmp, v3, Sp, Wp, L, False,
             ax, False)  # fmt: skip
        return False
    return _one(xh, P, xt, N, out, e, eps, cnt, cols, vals, C, Rt, Lb, w, U, u, Y, D, Dt, R, dq, tmp, v3, Sp, Wp, Uf,
                given, ax, given and centred)  # fmt: skip


@njit(**_JIT)
def nees_batch(x_hat, P, x_true, attitude, Rg):
    """NEES ``(B, 8)`` in the order of ``KEYS`` (module docstring) and ``pd (B,)``; ``x_true`` per trial ``(B, n)``.

    ``P``: the aligned error state's ``(B, n-1, n-1)``; the full state's ``(B, n, n)`` (a
    full-state filter's): the NEES of ``T P T^T``, ``T = aligned.error_map(x_hat)``, from ``P``'s
    own factor (``_one_full``), or, where ``P`` does not factorize, of ``T P T^T`` itself
    (``_map_full``); or, with ``attitude``, the attitude error state's ``(B, n-1, n-1)``: the NEES of
    ``M^-1 P M^-T`` (``aligned.from_attitude_chart``, ``M = T_attitude S_aligned``), from ``P``'s own
    factor (``_one_att``), or where ``P`` does not factorize of ``M^-1 P M^-T`` itself, with
    ``M^-1 = T_aligned S_attitude`` at the estimate: for a unit quaternion the two charts' maps
    are exact inverses, so no solve (``mc.trial.aligned_covariance``). ``pd``: the estimate and
    covariance are finite and ``P`` (as given) is positive definite (its Cholesky factorization
    went through). Every NEES is NaN where the state or ``P`` is not finite, or the aligned
    covariance is not positive definite.

    ``Rg``: ``(B, m, m)``, square roots ``R = J U`` of ``P = R^T R`` (the rows of ``P``'s upper Cholesky
    factor ``U`` in reverse order) where the caller has them (the compiled update's ``R+``), or
    ``(0, m, m)``. A trial's is used where the diagonal of ``U`` is finite and positive
    (``_factor_given``; the update marks a missing one with NaN): ``P`` is then positive definite
    (``pd``) and is not factorized again.
    """
    B = x_hat.shape[0]
    out = np.full((B, 8), np.nan)
    pd = np.zeros(B, np.bool_)
    own = _nees_scratch(x_hat.shape[1], P.shape[1])
    have = Rg.shape[0] == B
    # borrowed (_refs: no atomic reference counts in the per-trial views and calls); the scratch kept to the end
    ws = borrow(own)
    x_hat, P, x_true, Rg, ob = borrow((x_hat, P, x_true, Rg, out))
    for t in range(B):
        pd[t] = _nees_one(x_hat[t], P[t], x_true[t], attitude, Rg[t] if have else ws.Rf, have, ob[t], ws, False)
    keep(own)
    return out, pd


def nees_report(x_hat: np.ndarray, P: np.ndarray, x_true: np.ndarray, attitude: bool = False) -> dict[str, np.ndarray]:
    """``core.aligned.nees_report`` on the compiled kernel (same keys, same values to round-off); ``attitude``:
    ``P`` (``B, n-1, n-1``) is the attitude error state's (``mc.trial.aligned_covariance``)."""
    return nees_and_pd(x_hat, P, x_true, attitude)[0]


def nees_and_pd(x_hat: np.ndarray, P: np.ndarray, x_true: np.ndarray, attitude: bool = False,
                P_factor: np.ndarray | None = None) -> tuple[dict[str, np.ndarray], np.ndarray]:  # fmt: skip
    """``nees_report`` and, per trial, whether ``(x_hat, P)`` is finite with ``P`` positive definite.

    ``P_factor``: square roots of ``P`` as the compiled update gives them (``nees_batch``'s ``Rg``), or None."""
    x_hat, P = _writable(x_hat), _writable(P)
    if P_factor is None:
        Rg = np.empty((0,) + P.shape[1:])
    elif P_factor.shape == P.shape:
        Rg = _writable(P_factor)
    else:
        raise ValueError(f"P_factor {P_factor.shape} is not shaped as P {P.shape}")
    out, pd = nees_batch(x_hat, P, _writable(np.broadcast_to(x_true, x_hat.shape)), bool(attitude), Rg)
    return {k: out[:, j] for j, k in enumerate(KEYS)}, pd
