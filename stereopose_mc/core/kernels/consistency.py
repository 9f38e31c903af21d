"""Compiled (Numba) NEES of an aligned-chart estimate: the twin of ``core.aligned.nees_report``.

Per trial, from the estimate ``x_hat``, the covariance ``P`` of its aligned error state and
the truth ``x_true`` (docs/filters.md, Consistency):

- ``e = local_aligned(x_hat, x_true)``; full NEES ``e^T P^-1 e`` (``n - 1`` dof);
- gauge-projected NEES of ``W e`` with ``W P W^T``, ``W`` the differences of every point's
  ``e_Pi`` from the first point's (``n - 4`` rows, annihilating the common ``e_P``): the same
  number as with ``core.aligned.gauge_complement`` (a NEES of ``z`` does not change when ``z``
  is replaced by ``A z``, ``A`` invertible), for a sparse ``W``;
- the block NEES of the attitude-chart error ``eps = local_attitude(x_true, x_hat)`` with the
  blocks of ``M P M^T``, ``M = T_attitude S_aligned`` at ``x_hat``, written out:
  ``d rho = e_c - D mean(e_P)``, ``d rho_dot = e_cdot + [v x] e_omega - [omega x] D mean(e_P)``
  (``v = D P_bar``), ``a = D delta``, ``d P_i = e_Pi + [P_i x] delta``, identity on ``omega``
  and ``k``.

Products with ``M`` and ``W`` skip their zeros (a few per row); the three symmetric systems
are solved by the Cholesky of ``core.kernels.update``. A trial whose covariance is not
positive definite (or whose state is not finite) gets NaN, as ``errorstate.mahalanobis2``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .model import _dcm
from .update import _cholesky

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")

KEYS = ("nees", "nees_gauge", "nees_rho", "nees_rho_dot", "nees_omega", "nees_attitude", "nees_feature_points",
        "nees_k")  # fmt: skip


@njit(**_JIT)
def _mahalanobis(e, P, L, w):
    """``e^T P^-1 e`` by Cholesky (``L``, ``w`` scratch); NaN if ``P`` is not positive definite."""
    n = e.shape[0]
    if not _cholesky(P, L):
        return np.nan
    s = 0.0
    for i in range(n):
        t = e[i]
        for k in range(i):
            t -= L[i, k] * w[k]
        w[i] = t / L[i, i]
        s += w[i] * w[i]
    return s


@njit(**_JIT)
def _sandwich(M, rows, P, Y, out):
    """``out = M[rows] P M[rows]^T`` skipping the zeros of ``M`` (``Y`` scratch, ``len(rows) x n``)."""
    m, n = rows.shape[0], P.shape[0]
    for a in range(m):
        r = rows[a]
        for c in range(n):
            Y[a, c] = 0.0
        for k in range(n):
            v = M[r, k]
            if v != 0.0:
                for c in range(n):
                    Y[a, c] += v * P[k, c]
    for a in range(m):
        for b in range(a + 1):
            s = 0.0
            rb = rows[b]
            for k in range(n):
                v = M[rb, k]
                if v != 0.0:
                    s += Y[a, k] * v
            out[a, b] = s
            out[b, a] = s


@njit(**_JIT)
def _qmul(p, q, out):
    out[0] = p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3]
    out[1] = p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2]
    out[2] = p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1]
    out[3] = p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0]


@njit(**_JIT)
def _one(xh, P, xt, N, out, e, eps, M, W, S, L, w, Y, D, Dt, R, dq, tmp):
    n = xh.shape[0]
    ne = n - 1
    # --- aligned error at the estimate: e = local_aligned(x_hat, x_true)
    nh = math.sqrt(xh[9] ** 2 + xh[10] ** 2 + xh[11] ** 2 + xh[12] ** 2)
    nt = math.sqrt(xt[9] ** 2 + xt[10] ** 2 + xt[11] ** 2 + xt[12] ** 2)
    tmp[0], tmp[1], tmp[2], tmp[3] = xh[9] / nh, -xh[10] / nh, -xh[11] / nh, -xh[12] / nh
    _qmul(tmp, xt[9:13], dq)
    for j in range(4):
        dq[j] /= nt
    for j in range(3):
        e[9 + j] = 2.0 * dq[1 + j] / dq[0]
    _dcm(dq, R)
    _dcm(xh[9:13], D)
    _dcm(xt[9:13], Dt)
    pbh = np.zeros(3)
    pbt = np.zeros(3)
    for i in range(N):
        for r in range(3):
            pbh[r] += xh[13 + 3 * i + r] / N
            pbt[r] += xt[13 + 3 * i + r] / N
            s = 0.0
            for c in range(3):
                s += R[r, c] * xt[13 + 3 * i + c]
            e[12 + 3 * i + r] = s - xh[13 + 3 * i + r]
    vh = np.zeros(3)
    vt = np.zeros(3)
    for r in range(3):
        for c in range(3):
            vh[r] += D[r, c] * pbh[c]
            vt[r] += Dt[r, c] * pbt[c]
    for r in range(3):
        e[6 + r] = xt[6 + r] - xh[6 + r]
        e[r] = (xt[r] + vt[r]) - (xh[r] + vh[r])
    wh, wt = xh[6:9], xt[6:9]
    ch = np.empty(3)
    ct = np.empty(3)
    ch[0], ch[1], ch[2] = wh[1] * vh[2] - wh[2] * vh[1], wh[2] * vh[0] - wh[0] * vh[2], wh[0] * vh[1] - wh[1] * vh[0]
    ct[0], ct[1], ct[2] = wt[1] * vt[2] - wt[2] * vt[1], wt[2] * vt[0] - wt[0] * vt[2], wt[0] * vt[1] - wt[1] * vt[0]
    for r in range(3):
        e[3 + r] = (xt[3 + r] + ct[r]) - (xh[3 + r] + ch[r])
    for j in range(2):
        e[12 + 3 * N + j] = xt[13 + 3 * N + j] - xh[13 + 3 * N + j]
    out[0] = _mahalanobis(e, P, L, w)
    # --- gauge-projected: W e, W P W^T
    ng = ne - 3
    for r in range(ng):
        for c in range(ne):
            W[r, c] = 0.0
    for r in range(12):
        W[r, r] = 1.0
    for i in range(1, N):
        for j in range(3):
            W[12 + 3 * (i - 1) + j, 12 + 3 * i + j] = 1.0
            W[12 + 3 * (i - 1) + j, 12 + j] = -1.0
    for j in range(2):
        W[ng - 2 + j, ne - 2 + j] = 1.0
    rows = np.arange(ng)
    _sandwich(W, rows, P, Y, S)
    z = np.empty(ng)
    for r in range(ng):
        s = 0.0
        for c in range(ne):
            if W[r, c] != 0.0:
                s += W[r, c] * e[c]
        z[r] = s
    out[1] = _mahalanobis(z, S[:ng, :ng], L[:ng, :ng], w)
    # --- attitude-chart error, anchored at the truth: x_hat = x_true [+] eps
    for r in range(9):
        eps[r] = xh[r] - xt[r]
    for r in range(12, ne):
        eps[r] = xh[r + 1] - xt[r + 1]
    tmp[0], tmp[1], tmp[2], tmp[3] = xt[9] / nt, -xt[10] / nt, -xt[11] / nt, -xt[12] / nt
    _qmul(xh[9:13], tmp, dq)
    for j in range(3):
        eps[9 + j] = 2.0 * (dq[1 + j] / nh) / (dq[0] / nh)
    # --- M = d eps / d e at x_hat (rows of the attitude chart, columns of the aligned one)
    for r in range(ne):
        for c in range(ne):
            M[r, c] = 0.0
    for r in range(3):
        M[r, r] = 1.0  # d rho / d e_c
        M[3 + r, 3 + r] = 1.0  # d rho_dot / d e_cdot
        M[6 + r, 6 + r] = 1.0
        for c in range(3):
            M[9 + r, 9 + c] = D[r, c]  # a = D delta
    # [v x] on e_omega in rho_dot
    M[3, 7], M[3, 8] = -vh[2], vh[1]
    M[4, 6], M[4, 8] = vh[2], -vh[0]
    M[5, 6], M[5, 7] = -vh[1], vh[0]
    OD = np.empty((3, 3))  # [omega x] D
    for c in range(3):
        OD[0, c] = wh[1] * D[2, c] - wh[2] * D[1, c]
        OD[1, c] = wh[2] * D[0, c] - wh[0] * D[2, c]
        OD[2, c] = wh[0] * D[1, c] - wh[1] * D[0, c]
    for i in range(N):
        p = xh[13 + 3 * i : 16 + 3 * i]
        for r in range(3):
            for c in range(3):
                M[r, 12 + 3 * i + c] = -D[r, c] / N
                M[3 + r, 12 + 3 * i + c] = -OD[r, c] / N
            M[12 + 3 * i + r, 12 + 3 * i + r] = 1.0
        # [P_i x] on delta
        M[12 + 3 * i, 10], M[12 + 3 * i, 11] = -p[2], p[1]
        M[13 + 3 * i, 9], M[13 + 3 * i, 11] = p[2], -p[0]
        M[14 + 3 * i, 9], M[14 + 3 * i, 10] = -p[1], p[0]
    for j in range(2):
        M[ne - 2 + j, ne - 2 + j] = 1.0
    starts = (0, 3, 6, 9, 12, 12 + 3 * N)
    stops = (3, 6, 9, 12, 12 + 3 * N, ne)
    for b in range(6):
        m = stops[b] - starts[b]
        rows_b = np.arange(starts[b], stops[b])
        _sandwich(M, rows_b, P, Y, S)
        out[2 + b] = _mahalanobis(eps[starts[b] : stops[b]], S[:m, :m], L[:m, :m], w)


@njit(**_JIT)
def nees_batch(x_hat, P, x_true):
    """NEES ``(B, 8)`` in the order of ``KEYS`` (module docstring); ``x_true`` per trial ``(B, n)``."""
    B, n = x_hat.shape
    ne = n - 1
    N = (n - 15) // 3
    out = np.full((B, 8), np.nan)
    e = np.empty(ne)
    eps = np.empty(ne)
    M = np.empty((ne, ne))
    W = np.empty((ne - 3, ne))
    S = np.empty((ne, ne))
    L = np.empty((ne, ne))
    w = np.empty(ne)
    Y = np.empty((ne, ne))
    D = np.empty((3, 3))
    Dt = np.empty((3, 3))
    R = np.empty((3, 3))
    dq = np.empty(4)
    tmp = np.empty(4)
    for t in range(B):
        ok = True
        for j in range(n):
            if not (math.isfinite(x_hat[t, j]) and math.isfinite(x_true[t, j])):
                ok = False
        for r in range(ne):
            for c in range(ne):
                if not math.isfinite(P[t, r, c]):
                    ok = False
        if ok:
            _one(x_hat[t], P[t], x_true[t], N, out[t], e, eps, M, W, S, L, w, Y, D, Dt, R, dq, tmp)
    return out


def nees_report(x_hat: np.ndarray, P: np.ndarray, x_true: np.ndarray) -> dict[str, np.ndarray]:
    """``core.aligned.nees_report`` on the compiled kernel (same keys, same values to round-off)."""
    x_hat = np.ascontiguousarray(x_hat, dtype=float)
    out = nees_batch(x_hat, np.ascontiguousarray(P, dtype=float),
                     np.ascontiguousarray(np.broadcast_to(x_true, x_hat.shape), dtype=float))  # fmt: skip
    return {k: out[:, j] for j, k in enumerate(KEYS)}
