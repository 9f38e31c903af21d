"""Compiled (Numba) twins of ``core.aligned`` and of the aligned error-state step of ``filters/mekf.py``.

The numpy functions are the reference (their docstrings give the equations); here, one
trial at a time, float64, ``nogil``, ``cache=True`` (the batch entry points of both charts,
``chart = 1`` here, are in ``core.kernels.charts``):

- ``_chart``, ``_local``, ``_chart_jacobian`` (``S = dx/de`` at any ``e``), ``_error_map``
  (``T = de/dx``): ``core.aligned.chart``, ``local``, ``chart_jacobian``, ``error_map``;
- ``predict_covariance_batch``: ``P- = Phi_e P Phi_e^T + T(x-) diag(Q) T(x-)^T``,
  ``Phi_e = T(x-) Phi S(x+)`` (``mekf.predict``). ``Phi`` is the identity but for its
  13 x 15 block (``model.transition_reduced_batch``), ``S`` and ``T`` are identity-like with
  a few dense blocks, and so ``Phi_e`` is sparse but for its ``e_c, e_cdot`` rows (in case B
  about 360 of 841 entries): ``Phi_e`` is formed from the non-zeros of ``T`` against the
  rows of ``Phi S``, then ``P-`` as two sparse-times-dense products, lower triangle only;
- ``_measure_aligned``: ``h(x_ref [+] e)`` and the row-sparse ``H_e = H(x_ref [+] e) S(x_ref, e)``
  (``mekf.error_measurement``), from ``model._measure_one`` at the charted state.

**The row-sparse ``H_e``.** A feature's position and velocity in ``L`` are
``c + D_ref (u_i - u_bar)`` and ``c_dot + omega x D_ref (u_i - u_bar)`` (``u_i = P_i,ref + e_Pi``,
``core.aligned``): its rows depend on ``e_c, e_cdot, e_omega``, on its own ``e_Pi`` and, through
the centroid ``u_bar``, on every ``e_Pj`` by the same 3 x 3 block, and not on ``delta`` (in
exact arithmetic; ``H S`` in numpy leaves round-off ~1e-17 there, which this kernel does
not form). So a feature row is stored as 15 values: ``e_c, e_cdot, e_omega`` (9), its own
``e_Pi`` (3) and the common block (3), whose columns ``ne, ne+1, ne+2`` are *virtual*:
they stand for the sum of the 3 columns of every point (``virtual_rows`` appends to a matrix
``M`` those sums of rows, so that ``H_e M = sum_k h_k M_aug[c_k]``). The 3 pseudo rows see
``e_omega, delta, e_k`` (8 values). Rows are ``NNZ = 16`` wide (padding: value 0, column 0)
like those of ``model.measure_batch``, so that ``core.kernels.update`` runs the EKF and the
IEKF on either.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import attitude as _att
from ._refs import borrow, keep
from .attitude import _qmul, _quat_times, _small_quaternion, _small_quaternion_jacobian
from ..layout import (CHART_ALIGNED, COMMON, E_OMEGA, E_POINTS, E_RHO, E_RHO_DOT, E_ROT, E_SHIFT, K_SIZE, OMEGA,
                      POINTS, QUAT, R_K, REDUCED, RHO, RHO_DOT, VEC, e_n_points)  # fmt: skip
from .model import H_POINT, NNZ, Q_END, _dcm, _dcm_derivative, _measure_one, n_measurements, row_columns
from .model import n_points as _n_points
from .rows import _copy_row, _mirror_lower, _row_nonzeros, _sparse_rows_product
from .whiten import LARGE_N

_e_n_points = njit(inline="always", error_model="numpy")(e_n_points)

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")

DELTA = E_ROT  # the body-frame rotation ``delta`` of the aligned error state
D_END = DELTA + VEC
# a feature row of the row-sparse H_e holds e_c, e_cdot, e_omega, then its point's 3 values, then the 3 virtual ones
HR_POINT = E_OMEGA + VEC
HR_VIRTUAL = HR_POINT + VEC


@njit(**_JIT)
def _point_mean(x, N, pb):
    """``pb = P_bar``, the mean of the ``N`` feature points of state ``x``."""
    for a in range(3):
        pb[a] = 0.0
    for i in range(N):
        for a in range(3):
            pb[a] += x[POINTS + VEC * i + a]
    for a in range(3):
        pb[a] /= N


@njit(**_JIT)
def _centroid_ref(xr, N, Dref, v):
    """``D_ref = D(q_ref)`` and ``v = D_ref P_bar,ref``; returns nothing (fills both)."""
    _dcm(xr[QUAT:Q_END], Dref)
    own = np.empty(3)
    pb = borrow(own)  # (_refs; kept to the end)
    _point_mean(xr, N, pb)
    for a in range(3):
        v[a] = Dref[a, 0] * pb[0] + Dref[a, 1] * pb[1] + Dref[a, 2] * pb[2]
    keep(own)


@njit(**_JIT)
def _chart(xr, e, out, Dref, R, v):
    """``out = x_ref [+] e`` (``aligned.chart``); also ``D_ref``, ``R = R(dq(delta))`` and ``v = D_ref u_bar``."""
    n = xr.shape[0]
    N = _n_points(n)
    _centroid_ref(xr, N, Dref, v)
    w0, w1, w2 = xr[OMEGA], xr[OMEGA + 1], xr[OMEGA + 2]
    c0, c1, c2 = xr[RHO] + v[0], xr[RHO + 1] + v[1], xr[RHO + 2] + v[2]
    d0 = xr[RHO_DOT] + (w1 * v[2] - w2 * v[1])
    d1 = xr[RHO_DOT + 1] + (w2 * v[0] - w0 * v[2])
    d2 = xr[RHO_DOT + 2] + (w0 * v[1] - w1 * v[0])
    own = np.zeros(7)
    dq, ub = borrow((own[:4], own[4:]))  # (_refs; kept to the end)
    _small_quaternion(e[DELTA:D_END], dq)
    _qmul(xr[QUAT:Q_END], dq, out[QUAT:Q_END])  # q_ref (x) dq(delta)
    _dcm(dq, R)
    for i in range(N):
        p, ep = POINTS + VEC * i, E_POINTS + VEC * i
        u0 = xr[p] + e[ep]
        u1 = xr[p + 1] + e[ep + 1]
        u2 = xr[p + 2] + e[ep + 2]
        ub[0] += u0
        ub[1] += u1
        ub[2] += u2
        for a in range(3):  # R^T u
            out[p + a] = R[0, a] * u0 + R[1, a] * u1 + R[2, a] * u2
    for a in range(3):
        ub[a] /= N
    for a in range(3):
        out[OMEGA + a] = xr[OMEGA + a] + e[E_OMEGA + a]
        v[a] = Dref[a, 0] * ub[0] + Dref[a, 1] * ub[1] + Dref[a, 2] * ub[2]
    for j in range(n - K_SIZE, n):
        out[j] = xr[j] + e[j - E_SHIFT]
    w0, w1, w2 = out[OMEGA], out[OMEGA + 1], out[OMEGA + 2]
    out[RHO] = c0 + e[E_RHO] - v[0]
    out[RHO + 1] = c1 + e[E_RHO + 1] - v[1]
    out[RHO + 2] = c2 + e[E_RHO + 2] - v[2]
    out[RHO_DOT] = d0 + e[E_RHO_DOT] - (w1 * v[2] - w2 * v[1])
    out[RHO_DOT + 1] = d1 + e[E_RHO_DOT + 1] - (w2 * v[0] - w0 * v[2])
    out[RHO_DOT + 2] = d2 + e[E_RHO_DOT + 2] - (w0 * v[1] - w1 * v[0])
    keep(own)


@njit(**_JIT)
def _local(xh, xt, e, D, Dt, R, dq, tmp, v3):
    """``e = local(x_ref, x)`` (``aligned.local``) with ``xh`` the reference and ``xt`` the state; returns
    ``(|q_ref|, |q|)`` and leaves ``D = D(q_ref)``, ``Dt = D(q)``, ``R = D(dq)`` and, in the rows of ``v3``,
    ``P_bar_ref, P_bar, v_ref = D P_bar_ref, v, [omega_ref x] v_ref, [omega x] v`` (``core.kernels.consistency``
    reads ``D`` and ``v_ref``)."""
    N = _n_points(xh.shape[0])
    q = QUAT
    nh = math.sqrt(xh[q] ** 2 + xh[q + 1] ** 2 + xh[q + 2] ** 2 + xh[q + 3] ** 2)
    nt = math.sqrt(xt[q] ** 2 + xt[q + 1] ** 2 + xt[q + 2] ** 2 + xt[q + 3] ** 2)
    tmp[0], tmp[1], tmp[2], tmp[3] = xh[q] / nh, -xh[q + 1] / nh, -xh[q + 2] / nh, -xh[q + 3] / nh
    _qmul(tmp, xt[QUAT:Q_END], dq)
    for j in range(4):
        dq[j] /= nt
    for j in range(3):
        e[DELTA + j] = 2.0 * dq[1 + j] / dq[0]
    _dcm(dq, R)
    _dcm(xh[QUAT:Q_END], D)
    _dcm(xt[QUAT:Q_END], Dt)
    pbh, pbt, vh, vt, ch, ct = v3[0], v3[1], v3[2], v3[3], v3[4], v3[5]
    for r in range(3):
        pbh[r] = 0.0
        pbt[r] = 0.0
        vh[r] = 0.0
        vt[r] = 0.0
    for i in range(N):
        p, ep = POINTS + VEC * i, E_POINTS + VEC * i
        for r in range(3):
            pbh[r] += xh[p + r] / N
            pbt[r] += xt[p + r] / N
            s = 0.0
            for c in range(3):
                s += R[r, c] * xt[p + c]
            e[ep + r] = s - xh[p + r]
    for r in range(3):
        for c in range(3):
            vh[r] += D[r, c] * pbh[c]
            vt[r] += Dt[r, c] * pbt[c]
    for r in range(3):
        e[E_OMEGA + r] = xt[OMEGA + r] - xh[OMEGA + r]
        e[E_RHO + r] = (xt[RHO + r] + vt[r]) - (xh[RHO + r] + vh[r])
    wh, wt = xh[OMEGA : OMEGA + VEC], xt[OMEGA : OMEGA + VEC]
    ch[0], ch[1], ch[2] = wh[1] * vh[2] - wh[2] * vh[1], wh[2] * vh[0] - wh[0] * vh[2], wh[0] * vh[1] - wh[1] * vh[0]
    ct[0], ct[1], ct[2] = wt[1] * vt[2] - wt[2] * vt[1], wt[2] * vt[0] - wt[0] * vt[2], wt[0] * vt[1] - wt[1] * vt[0]
    for r in range(3):
        e[E_RHO_DOT + r] = (xt[RHO_DOT + r] + ct[r]) - (xh[RHO_DOT + r] + ch[r])
    for j in range(POINTS + VEC * N, POINTS + VEC * N + K_SIZE):
        e[j - E_SHIFT] = xt[j] - xh[j]
    return nh, nt


@njit(**_JIT)
def _chart_jacobian(xr, e, S):
    """``S = d (x_ref [+] e) / d e`` (``n x n-1``, ``aligned.chart_jacobian``), written in full."""
    n = xr.shape[0]
    N = _n_points(n)
    S[:, :] = 0.0
    own = np.zeros(103)  # one allocation for the scratch below (ub: zeros)
    ws = borrow(own)  # (_refs; kept to the end)
    Dref, v, dq = ws[0:9].reshape((3, 3)), ws[9:12], ws[12:16]
    Sq, R, dR = ws[16:28].reshape((4, 3)), ws[28:37].reshape((3, 3)), ws[37:73].reshape((4, 3, 3))
    w, W, ub, u, dRtu = ws[73:76], ws[76:85].reshape((3, 3)), ws[85:88], ws[88:91], ws[91:103].reshape((3, 4))
    _centroid_ref(xr, N, Dref, v)  # D_ref (v is recomputed below at u)
    _small_quaternion(e[DELTA:D_END], dq)
    _small_quaternion_jacobian(e[DELTA:D_END], Sq)
    _quat_times(xr[QUAT:Q_END], Sq, S[QUAT:Q_END, DELTA:D_END], 1.0)
    _dcm_derivative(dq, R, dR)
    for a in range(3):
        w[a] = xr[OMEGA + a] + e[E_OMEGA + a]
    for c in range(3):  # W = [w x] D_ref / N
        W[0, c] = (w[1] * Dref[2, c] - w[2] * Dref[1, c]) / N
        W[1, c] = (w[2] * Dref[0, c] - w[0] * Dref[2, c]) / N
        W[2, c] = (w[0] * Dref[1, c] - w[1] * Dref[0, c]) / N
    for i in range(N):
        r0, c0 = POINTS + VEC * i, E_POINTS + VEC * i
        for a in range(3):
            u[a] = xr[r0 + a] + e[c0 + a]
            ub[a] += u[a]
        for a in range(3):
            for b in range(3):
                S[r0 + a, c0 + b] = R[b, a]
                S[RHO + a, c0 + b] = -Dref[a, b] / N
                S[RHO_DOT + a, c0 + b] = -W[a, b]
            for j in range(4):  # (dR_j^T u)_a
                dRtu[a, j] = dR[j, 0, a] * u[0] + dR[j, 1, a] * u[1] + dR[j, 2, a] * u[2]
        for a in range(3):
            for j in range(3):
                S[r0 + a, DELTA + j] = (dRtu[a, 0] * Sq[0, j] + dRtu[a, 1] * Sq[1, j] + dRtu[a, 2] * Sq[2, j]
                                    + dRtu[a, 3] * Sq[3, j])  # fmt: skip
    for a in range(3):
        ub[a] /= N
    for a in range(3):
        v[a] = Dref[a, 0] * ub[0] + Dref[a, 1] * ub[1] + Dref[a, 2] * ub[2]
    for a in range(3):
        S[RHO + a, E_RHO + a] = 1.0
        S[RHO_DOT + a, E_RHO_DOT + a] = 1.0
        S[OMEGA + a, E_OMEGA + a] = 1.0
    # [v x] on rho_dot <- e_omega
    r, c = RHO_DOT, E_OMEGA
    S[r, c + 1], S[r, c + 2] = -v[2], v[1]
    S[r + 1, c], S[r + 1, c + 2] = v[2], -v[0]
    S[r + 2, c], S[r + 2, c + 1] = -v[1], v[0]
    for j in range(n - K_SIZE, n):
        S[j, j - E_SHIFT] = 1.0
    keep(own)


@njit(**_JIT)
def _error_map(xr, T):
    """``T = d e / d x`` at ``x_ref`` (``n-1 x n``, ``aligned.error_map``), written in full."""
    n = xr.shape[0]
    N = _n_points(n)
    T[:, :] = 0.0
    q = xr[QUAT:Q_END]
    qn = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    q0, q1, q2, q3 = q[0] / qn, q[1] / qn, q[2] / qn, q[3] / qn
    own = np.empty(75)  # one allocation for the scratch below
    ws = borrow(own)  # (_refs; kept to the end)
    Xi = ws[0:12].reshape((3, 4))  # 2 [L(q^*)]_vec
    Xi[0, 0], Xi[0, 1], Xi[0, 2], Xi[0, 3] = -2.0 * q1, 2.0 * q0, 2.0 * q3, -2.0 * q2
    Xi[1, 0], Xi[1, 1], Xi[1, 2], Xi[1, 3] = -2.0 * q2, -2.0 * q3, 2.0 * q0, 2.0 * q1
    Xi[2, 0], Xi[2, 1], Xi[2, 2], Xi[2, 3] = -2.0 * q3, 2.0 * q2, -2.0 * q1, 2.0 * q0
    D = ws[12:21].reshape((3, 3))
    dD = ws[21:57].reshape((4, 3, 3))
    _dcm_derivative(q, D, dD)
    pb = ws[57:60]
    _point_mean(xr, N, pb)
    v = ws[60:63]
    dv = ws[63:75].reshape((3, 4))
    for a in range(3):
        v[a] = D[a, 0] * pb[0] + D[a, 1] * pb[1] + D[a, 2] * pb[2]
        for j in range(4):
            dv[a, j] = dD[j, a, 0] * pb[0] + dD[j, a, 1] * pb[1] + dD[j, a, 2] * pb[2]
    w0, w1, w2 = xr[OMEGA], xr[OMEGA + 1], xr[OMEGA + 2]
    for a in range(3):
        for j in range(4):
            T[DELTA + a, QUAT + j] = Xi[a, j]
    ec, ed = E_RHO, E_RHO_DOT
    for i in range(N):
        r0, c0 = E_POINTS + VEC * i, POINTS + VEC * i
        P0, P1, P2 = xr[c0], xr[c0 + 1], xr[c0 + 2]
        for j in range(4):  # -[P_i x] Xi
            T[r0, QUAT + j] = -(-P2 * Xi[1, j] + P1 * Xi[2, j])
            T[r0 + 1, QUAT + j] = -(P2 * Xi[0, j] - P0 * Xi[2, j])
            T[r0 + 2, QUAT + j] = -(-P1 * Xi[0, j] + P0 * Xi[1, j])
        for a in range(3):
            T[r0 + a, c0 + a] = 1.0
            for b in range(3):
                T[ec + a, c0 + b] = D[a, b] / N
        for b in range(3):  # [w x] D / N
            T[ed, c0 + b] = (w1 * D[2, b] - w2 * D[1, b]) / N
            T[ed + 1, c0 + b] = (w2 * D[0, b] - w0 * D[2, b]) / N
            T[ed + 2, c0 + b] = (w0 * D[1, b] - w1 * D[0, b]) / N
    for j in range(4):
        T[ec, QUAT + j], T[ec + 1, QUAT + j], T[ec + 2, QUAT + j] = dv[0, j], dv[1, j], dv[2, j]
        T[ed, QUAT + j] = w1 * dv[2, j] - w2 * dv[1, j]
        T[ed + 1, QUAT + j] = w2 * dv[0, j] - w0 * dv[2, j]
        T[ed + 2, QUAT + j] = w0 * dv[1, j] - w1 * dv[0, j]
    for a in range(3):
        T[ec + a, RHO + a] = 1.0
        T[ed + a, RHO_DOT + a] = 1.0
        T[E_OMEGA + a, OMEGA + a] = 1.0
    # -[v x] on e_cdot <- omega
    c = OMEGA
    T[ed, c + 1], T[ed, c + 2] = v[2], -v[1]
    T[ed + 1, c], T[ed + 1, c + 2] = -v[2], v[0]
    T[ed + 2, c], T[ed + 2, c + 1] = v[1], -v[0]
    for j in range(n - K_SIZE, n):
        T[j - E_SHIFT, j] = 1.0
    keep(own)


@njit(**_JIT)
def _apply_error_map(Tm, N, src, dst, Sp, lower=False):
    """``dst = T src`` for ``T = aligned.error_map`` (``Tm``, ``n-1 x n``) from its non-zeros, ``src (n, m)``.

    Row ``r`` of ``T`` is an identity entry (column ``r`` for ``r < 9``, ``r + 1`` from the
    points on, none for ``delta``'s rows 9-11), its quaternion block (columns 9-12; zero on
    ``omega``'s and ``k``'s rows), ``-[v x]`` on ``omega`` in ``e_cdot``'s rows, and, in
    ``e_c``'s and ``e_cdot``'s rows, the same 3 coefficients on every point (``D / N`` and
    ``[omega x] D / N``): those take the point rows of ``src`` summed once (``Sp``). Each row
    of ``dst`` is ~6 scaled rows of ``src`` instead of ``n``: ``T P T^T`` as
    ``T (T P)^T`` costs ~``12 n^2`` instead of ``2 n^3``.

    ``lower``: only the lower triangle of ``dst`` (square), the columns ``c <= r``, for a
    symmetric product whose upper triangle is mirrored after: each entry is the same sum in
    the same order as in the full product (the same bits), for about half the work.
    """
    ne, mm = dst.shape
    ms = min(E_OMEGA, mm) if lower else mm  # the columns of the point sums that the rows read (e_c, e_cdot only)
    for a in range(3):
        for c in range(ms):
            Sp[a, c] = 0.0
    for i in range(N):
        for a in range(3):
            for c in range(ms):
                Sp[a, c] += src[POINTS + VEC * i + a, c]
    for r in range(ne):
        m = min(r + 1, mm) if lower else mm
        if r < DELTA:
            _copy_row(dst, r, src, r, m)
        elif r < D_END:
            for c in range(m):
                dst[r, c] = 0.0
        else:
            _copy_row(dst, r, src, r + E_SHIFT, m)
        if r < E_OMEGA or (r >= DELTA and r < ne - K_SIZE):  # the quaternion block
            for j in range(QUAT, Q_END):
                t = Tm[r, j]
                for c in range(m):
                    dst[r, c] += t * src[j, c]
        if r < E_OMEGA:  # the points' mean
            for b in range(3):
                t = Tm[r, POINTS + b]
                for c in range(m):
                    dst[r, c] += t * Sp[b, c]
        if r >= E_RHO_DOT and r < E_OMEGA:  # -[v x] on omega
            for j in range(OMEGA, OMEGA + VEC):
                t = Tm[r, j]
                if j != r - E_RHO_DOT + OMEGA:
                    for c in range(m):
                        dst[r, c] += t * src[j, c]


# --- prediction -----------------------------------------------------------------


@njit(**_JIT)
def predict_covariance_batch(x, x_pred, Tb, P, Q, chart):
    """``P- = Phi_e P Phi_e^T + T(x-) diag(Q) T(x-)^T`` with ``Phi_e = T(x-) Phi S(x+)``, symmetric (``mekf.predict``).

    ``chart`` 1: the aligned error state (this module's ``S`` and ``T``); 2: the attitude error
    state (``core.kernels.attitude``'s).

    ``x (B, n)`` the posteriors at which ``F`` was evaluated, ``x_pred (B, n)`` the predicted
    states, ``Tb = Phi[:, 0:13, c] (B, 13, 15)`` (``model.transition_reduced_batch``; the rest
    of ``Phi`` is the identity), ``P (B, n-1, n-1)``, ``Q (B, n)`` the process noise's diagonal.
    ``Phi S`` is ``S`` but for its first 13 rows (``Tb S[c]``); ``Phi_e = T (Phi S)`` and ``T (diag(Q)
    T^T)`` from the non-zeros of the aligned chart's ``T`` (``_apply_error_map``: ~6 scaled rows
    per row, 2x faster than BLAS at ``n ~ 30``; the attitude chart's from its non-zeros too,
    ``attitude._apply_error_map``: a row or a sum of four per row), ``P- = Phi_e
    (Phi_e P)^T`` by BLAS, plus the noise term; its lower triangle mirrored (exactly symmetric).
    """
    B, n = x.shape
    ne = n - 1
    out = np.empty((B, ne, ne))
    S = np.empty((n, ne))
    T = np.empty((ne, n))
    QT = np.empty((n, ne))
    W = np.empty((ne, ne))
    Sp = np.empty((3, ne))  # _apply_error_map's point sums
    N = _n_points(n)
    PS = np.empty((n, ne))
    Sc = np.empty((REDUCED, ne))
    Y = np.empty((ne, ne))
    M = np.empty((ne, ne))
    Y2 = np.empty((ne, ne))
    nz = np.empty((ne, ne), np.int64)
    cnt = np.empty(ne, np.int64)
    e0 = np.zeros(ne)
    own = (S, T, QT, W, Sp, PS, Sc, Y, M, Y2, e0)  # borrowed below (_refs), kept to the end
    x, x_pred, Tb, P, Q, outb = borrow((x, x_pred, Tb, P, Q, out))
    S, T, QT, W, Sp, PS, Sc, Y, M, Y2, e0 = borrow(own)
    for b in range(B):
        if chart == CHART_ALIGNED:
            _chart_jacobian(x[b], e0, S)
            _error_map(x_pred[b], T)
        else:
            _att._chart_jacobian(x[b], e0, S)
            _att._error_map(x_pred[b], T)
        for a in range(COMMON, n):
            for j in range(ne):
                PS[a, j] = S[a, j]
        for j in range(ne):  # S[c], c = [0..12, n-2, n-1]
            for a in range(COMMON):
                Sc[a, j] = S[a, j]
            for a in range(K_SIZE):
                Sc[R_K + a, j] = S[n - K_SIZE + a, j]
        np.dot(Tb[b], Sc, PS[:COMMON])  # (Phi S)[0:13] = Tb S[c] (BLAS gemm)
        if chart == CHART_ALIGNED:  # Phi_e = T (Phi S) from the non-zeros of T
            _apply_error_map(T, N, PS, Y, Sp)
        else:  # Phi_e = T (Phi S) from the non-zeros of the attitude chart's T
            _att._apply_error_map(T, PS, Y)
        Pb = outb[b]
        if ne > LARGE_N:  # Phi_e is the identity but for a few rows: products from its rows' non-zeros
            _row_nonzeros(Y, nz, cnt)
            _sparse_rows_product(Y, nz, cnt, P[b], M, False)  # M = Phi_e P
            for r in range(ne):  # M^T
                for j in range(ne):
                    Y2[r, j] = M[j, r]
            _sparse_rows_product(Y, nz, cnt, Y2, Pb, True)  # Phi_e M^T, its lower triangle
        else:  # small states: BLAS is as fast
            np.dot(Y, P[b], M)  # M = Phi_e P
            np.dot(Y, M.T, Pb)  # Phi_e M^T
        for j in range(n):
            for r in range(ne):
                QT[j, r] = Q[b, j] * T[r, j]
        if chart == CHART_ALIGNED:  # T (diag(Q) T^T)
            _apply_error_map(T, N, QT, W, Sp, True)  # its lower triangle (added to P-'s below)
        else:
            _att._apply_error_map(T, QT, W, True)  # its lower triangle
        for r in range(ne):
            for j in range(r + 1):
                Pb[r, j] += W[r, j]
        _mirror_lower(Pb)
    keep(own)
    return out


# --- measurement ----------------------------------------------------------------


@njit(**_JIT)
def _measure_aligned(xr, e, model, alpha, compute_jac, hx, Hval, xt, D, dD):
    """``h(x_ref [+] e)`` and the row-sparse ``H_e`` of one trial (module docstring); ``xt``: the charted state.

    From ``model._measure_one``'s full-state rows at ``xt``: a feature's ``[rho, rho_dot,
    omega, q, P_i]`` columns become ``e_c = H_rho``, ``e_cdot = H_rho_dot``,
    ``e_omega = H_omega + H_rho_dot [v x]``, ``e_Pi = H_Pi R^T`` and the common block
    ``-(H_rho D_ref + H_rho_dot [omega x] D_ref) / N``; a pseudo row's ``[omega, q, k]``
    become ``e_omega``, ``delta = H_q L(q_ref) d dq/d delta``, ``e_k``.
    """
    N = _n_points(xr.shape[0])
    own = np.empty(70)  # one allocation for the scratch below
    ws = borrow(own)  # (_refs; kept to the ends)
    Dref = ws[0:9].reshape((3, 3))
    R = ws[9:18].reshape((3, 3))
    v = ws[18:21]
    _chart(xr, e, xt, Dref, R, v)
    _measure_one(xt, model, alpha, compute_jac, hx, Hval, D, dD)
    if not compute_jac:
        keep(own)
        return
    nf = n_measurements(model.vis.shape[0], model.disparity, False)  # the features' rows
    w0, w1, w2 = xt[OMEGA], xt[OMEGA + 1], xt[OMEGA + 2]
    WD = ws[21:30].reshape((3, 3))  # [omega x] D_ref / N
    for j in range(3):
        WD[0, j] = (w1 * Dref[2, j] - w2 * Dref[1, j]) / N
        WD[1, j] = (w2 * Dref[0, j] - w0 * Dref[2, j]) / N
        WD[2, j] = (w0 * Dref[1, j] - w1 * Dref[0, j]) / N
    h = ws[30 : 30 + NNZ]
    for r in range(nf):
        for k in range(NNZ):
            h[k] = Hval[r, k]
        # e_c = H_rho and e_cdot = H_rho_dot stay in their columns
        o, d, p = OMEGA, RHO_DOT, H_POINT
        Hval[r, E_OMEGA] = h[o] + (h[d + 1] * v[2] - h[d + 2] * v[1])
        Hval[r, E_OMEGA + 1] = h[o + 1] + (h[d + 2] * v[0] - h[d] * v[2])
        Hval[r, E_OMEGA + 2] = h[o + 2] + (h[d] * v[1] - h[d + 1] * v[0])
        for j in range(3):
            Hval[r, HR_POINT + j] = h[p] * R[j, 0] + h[p + 1] * R[j, 1] + h[p + 2] * R[j, 2]
            Hval[r, HR_VIRTUAL + j] = (-(h[RHO] * Dref[0, j] + h[RHO + 1] * Dref[1, j] + h[RHO + 2] * Dref[2, j]) / N
                                       - (h[d] * WD[0, j] + h[d + 1] * WD[1, j] + h[d + 2] * WD[2, j]))  # fmt: skip
        for k in range(HR_VIRTUAL + VEC, NNZ):
            Hval[r, k] = 0.0
    if model.pseudo:
        Sq = ws[46:58].reshape((4, 3))
        LSq = ws[58:70].reshape((4, 3))
        _small_quaternion_jacobian(e[DELTA:D_END], Sq)
        _quat_times(xr[QUAT:Q_END], Sq, LSq, 1.0)
        _att._pseudo_rows_rotated(Hval, nf, LSq, h)
    keep(own)


def measurement_columns(ne, vis, channels, pseudo):
    """Column indices ``(m, 16)`` of the row-sparse ``H_e``: a feature's rows see ``e_c, e_cdot, e_omega``,
    its point and the virtual point-sum columns ``ne, ne+1, ne+2``; the pseudo rows ``e_omega, delta, e_k``."""
    k = np.arange(ne - K_SIZE, ne)
    return row_columns(vis, channels, np.arange(E_ROT), E_POINTS, np.arange(ne, ne + VEC),
                       np.concatenate((np.arange(E_OMEGA, D_END), k)), pseudo)  # fmt: skip


@njit(**_JIT)
def virtual_rows(M, out):
    """``out[ne + a] = sum_j M[12 + 3 j + a]`` (``ne`` rows in ``M``; ``M`` may be ``out[:ne]``)."""
    ne = M.shape[0]
    N = _e_n_points(ne)
    for a in range(3):
        for j in range(M.shape[1]):
            out[ne + a, j] = 0.0
        for p in range(N):
            for j in range(M.shape[1]):
                out[ne + a, j] += M[E_POINTS + VEC * p + a, j]


def dense(Hval: np.ndarray, cols: np.ndarray, ne: int) -> np.ndarray:
    """Dense ``H_e (B, m, ne)`` from the row-sparse one: each virtual column added to every point's columns."""
    from .model import dense as dense_full

    H = dense_full(Hval, cols, ne + 3)
    for p in range(e_n_points(ne)):
        H[..., E_POINTS + VEC * p : E_POINTS + VEC * (p + 1)] += H[..., ne:]
    return np.ascontiguousarray(H[..., :ne])
