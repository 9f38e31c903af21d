"""Compiled (Numba) twins of the second-order measurement noise: the variance a row's linearization leaves out.

- ``flow_variance_batch``: the image-velocity rows' (``core.camera.flow_second_order_variance``);
- ``pseudo_variance_batch``: the inertia pseudo rows' (``core.inertia.pseudo_second_order_variance``);
- ``rate_noise_batch``: the prediction's ``Q`` with the rate dynamics' (``core.inertia.rate_second_order_variance``).

Both read the blocks they need straight from the filter's covariance ``P (B, ne, ne)`` (the full state's or an
error state's: ``omega`` at offset ``w0``, the points from ``p0``, ``k`` last; ``filters.relnav``'s
``flow_linearization_variance`` and ``pseudo_linearization_variance`` pick the same blocks), one trial at a time
with ``3 x 3`` products written out in a fixed order, so a trial's result does not depend on its batch.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..camera import CHANNELS
from ..layout import K_SIZE, OMEGA, POINTS, PSEUDO_ROWS, QUAT, QUAT_SIZE, RHO, VEC
from ._refs import borrow, keep
from .model import _dcm, n_channels as _n_channels, n_points as _n_points

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")

# the image-velocity channels among a feature's (core.camera.CHANNELS); dv_L equals dv_R
DU_R, DV_R, DU_L, DV_L = (CHANNELS.index(c) for c in ("du_r", "dv_r", "du_l", "dv_l"))
# the coordinate (x or z) an image velocity divides by y: du_* read x, dv_* read z
X_AXIS, Y_AXIS, Z_AXIS = 0, 1, 2


@njit(**_JIT)
def _mm3(A, B, out):
    """``out = A B`` of ``3 x 3`` matrices, each entry ``(a0 b0 + a1 b1) + a2 b2``."""
    for i in range(VEC):
        for j in range(VEC):
            out[i, j] = (A[i, 0] * B[0, j] + A[i, 1] * B[1, j]) + A[i, 2] * B[2, j]


@njit(**_JIT)
def _mmT3(A, B, out):
    """``out = A B^T`` of ``3 x 3`` matrices."""
    for i in range(VEC):
        for j in range(VEC):
            out[i, j] = (A[i, 0] * B[j, 0] + A[i, 1] * B[j, 1]) + A[i, 2] * B[j, 2]


@njit(**_JIT)
def _frobenius3(A, B, r0, c0):
    """``sum_kl A[k, l] B[r0 + k, c0 + l]``: ``tr(A B^T)`` against a ``3 x 3`` block of ``B``, read in place."""
    s = 0.0
    for k in range(VEC):
        s += (A[k, 0] * B[r0 + k, c0] + A[k, 1] * B[r0 + k, c0 + 1]) + A[k, 2] * B[r0 + k, c0 + 2]
    return s


@njit(**_JIT)
def _flow_M(r, a, pa, iy, M, K, Rx):
    """``M = [r x] K - [g x]`` of the image velocity ``f = (v_a y - p_a v_y) / y^2`` (``a`` the axis of ``p_a``).

    ``g = df/dv``: ``g_a = 1/y``, ``g_y = -p_a / y^2``, the third 0; ``K = d2f/dv dp``:
    ``K_ay = K_ya = -1/y^2``, ``K_yy = 2 p_a / y^3``, the rest 0 (``core.camera.flow_second_order_variance``).
    ``K`` and ``Rx`` are ``3 x 3`` scratch.
    """
    iy2 = iy * iy
    K[:] = 0.0
    K[a, Y_AXIS] = -iy2
    K[Y_AXIS, a] = -iy2
    K[Y_AXIS, Y_AXIS] = 2.0 * pa * iy2 * iy
    Rx[0, 0], Rx[0, 1], Rx[0, 2] = 0.0, -r[2], r[1]  # [r x]
    Rx[1, 0], Rx[1, 1], Rx[1, 2] = r[2], 0.0, -r[0]
    Rx[2, 0], Rx[2, 1], Rx[2, 2] = -r[1], r[0], 0.0
    _mm3(Rx, K, M)
    g = (iy if a == X_AXIS else 0.0, -pa * iy2, iy if a == Z_AXIS else 0.0)
    M[0, 1] += g[2]  # - [g x]
    M[0, 2] -= g[1]
    M[1, 0] -= g[2]
    M[1, 2] += g[0]
    M[2, 0] += g[1]
    M[2, 1] -= g[0]


@njit(**_JIT)
def _flow_variance(x, P, w0, p0, baseline, out, D, S_r, M, T, V, K, Rx):
    """``out (N, C)``: ``tr(M S_r M^T P_ww)`` per feature on ``du_R, dv_R, du_L`` (``dv_L = dv_R``), 0 elsewhere.

    ``r = D P_i``, ``rho_i = rho + r``, ``S_r = D P_pp[i] D^T`` (``P_pp[i]`` the point's ``3 x 3`` block of ``P``
    at ``p0 + 3 i``), ``P_ww`` the block at ``w0`` (``core.camera.flow_second_order_variance``). ``D ... Rx``: ``3 x 3``
    scratch.
    """
    _dcm(x[QUAT : QUAT + QUAT_SIZE], D)
    for i in range(out.shape[0]):
        o = POINTS + VEC * i
        r = ((D[0, 0] * x[o] + D[0, 1] * x[o + 1]) + D[0, 2] * x[o + 2],
             (D[1, 0] * x[o] + D[1, 1] * x[o + 1]) + D[1, 2] * x[o + 2],
             (D[2, 0] * x[o] + D[2, 1] * x[o + 1]) + D[2, 2] * x[o + 2])  # fmt: skip
        px, y, pz = x[RHO] + r[0], x[RHO + 1] + r[1], x[RHO + 2] + r[2]
        iy = 1.0 / y
        q0 = p0 + VEC * i
        for j in range(VEC):  # T = D P_pp[i]
            for m in range(VEC):
                T[j, m] = (D[j, 0] * P[q0, q0 + m] + D[j, 1] * P[q0 + 1, q0 + m]) + D[j, 2] * P[q0 + 2, q0 + m]
        _mmT3(T, D, S_r)
        for col, a, pa in ((DU_R, X_AXIS, px), (DV_R, Z_AXIS, pz), (DU_L, X_AXIS, px - baseline)):
            _flow_M(r, a, pa, iy, M, K, Rx)
            _mm3(M, S_r, T)
            _mmT3(T, M, V)
            out[i, col] = _frobenius3(V, P, w0, w0)
        out[i, DV_L] = out[i, DV_R]


@njit(**_JIT)
def flow_variance_batch(x, P, w0, p0, baseline, disparity, focal):
    """``(B, N, C)``: ``core.camera.flow_second_order_variance`` of every trial, times ``focal^2``, from the
    ``omega`` block of ``P`` at ``w0`` and the points' blocks from ``p0``."""
    B, n = x.shape
    out = np.zeros((B, _n_points(n), _n_channels(disparity)))
    own = np.empty((7, VEC, VEC))  # the 3 x 3 scratch D, S_r, M, T, V, K, Rx
    # borrowed (_refs: no atomic reference counts in the per-trial views and calls); the scratch kept to the end
    x, P, ob, ws = borrow((x, P, out, own))
    D, S_r, M, T, V, K, Rx = ws[0], ws[1], ws[2], ws[3], ws[4], ws[5], ws[6]
    f2 = focal * focal
    for b in range(B):
        _flow_variance(x[b], P[b], w0, p0, baseline, ob[b], D, S_r, M, T, V, K, Rx)
        if focal != 1.0:
            for i in range(ob.shape[1]):
                for c in range(ob.shape[2]):
                    ob[b, i, c] *= f2
    keep(own)
    return out


@njit(**_JIT)
def _euler_coefficients(k1, k2):
    """``c (3,)``, ``dc/dk (3, 2)``, ``d2c/dk2 (3, 2, 2)`` as nested tuples, of ``I^-1 (w x I w) = c * [w2 w3, w3 w1,
    w1 w2]`` with ``I = [e^k1, 1, e^-k2]`` (``core.inertia.euler_coefficients``)."""
    I1, I2, I3 = math.exp(k1), 1.0, math.exp(-k2)
    c = ((I3 - I2) / I1, (I1 - I3) / I2, (I2 - I1) / I3)
    r13, r31 = I3 / I1, I1 / I3
    dc = ((-c[0], -r13), (I1, I3), (-r31, c[2]))
    ddc = (((c[0], r13), (r13, r13)), ((I1, 0.0), (0.0, -I3)), ((-r31, -r31), (-r31, c[2])))
    return c, dc, ddc


@njit(**_JIT)
def _pseudo_variance(x, P, w0, nd, out, D, S, T, C_kw, A):
    """``out (3,)``: per pseudo row ``i`` (gyroscopic term ``c_i w_a w_b``, ``w_T = D^T (w + w_L)``)

        (c^2 + s_c^2) (S_aa S_bb + S_ab^2) + s_c^2 s_m^2 + cov(dc, dm)^2
          + 2 c (Cov(dw_a, dc) Cov(dw_b, dm) + Cov(dw_a, dm) Cov(dw_b, dc)) + m0^2/2 tr((c'' P_kk)^2)

    with ``S = D^T P_ww D``, ``Cov(dk, dw_T) = C_kw = P_kw D`` (``core.inertia.pseudo_second_order_variance``);
    ``P_ww`` the block of ``P`` at ``w0``, ``P_kk`` and ``P_kw`` from its last ``K_SIZE`` rows. ``D, S, T`` (``3 x 3``),
    ``C_kw`` (``2 x 3``), ``A`` (``2 x 2``): scratch."""
    k0 = P.shape[0] - K_SIZE
    n = x.shape[0]
    _dcm(x[QUAT : QUAT + QUAT_SIZE], D)
    W0, W1, W2 = x[OMEGA], x[OMEGA + 1], x[OMEGA + 2] + nd  # w + w_L
    wT = ((D[0, 0] * W0 + D[1, 0] * W1) + D[2, 0] * W2, (D[0, 1] * W0 + D[1, 1] * W1) + D[2, 1] * W2,
          (D[0, 2] * W0 + D[1, 2] * W1) + D[2, 2] * W2)  # fmt: skip
    for j in range(VEC):  # T = D^T P_ww, S = T D
        for m in range(VEC):
            T[j, m] = (D[0, j] * P[w0, w0 + m] + D[1, j] * P[w0 + 1, w0 + m]) + D[2, j] * P[w0 + 2, w0 + m]
    _mm3(T, D, S)
    for j in range(K_SIZE):
        for m in range(VEC):
            C_kw[j, m] = (P[k0 + j, w0] * D[0, m] + P[k0 + j, w0 + 1] * D[1, m]) + P[k0 + j, w0 + 2] * D[2, m]
    c, dc, ddc = _euler_coefficients(x[n - K_SIZE], x[n - K_SIZE + 1])
    for i in range(PSEUDO_ROWS):
        a, b = (i + 1) % VEC, (i + 2) % VEC  # the pair of body rates of row i: (1, 2), (2, 0), (0, 1)
        g0, g1 = dc[i]
        # u = Cov(dc, dw_T) = g C_kw; Sg = Cov(dw_T, dm) = S gm (gm = w_b e_a + w_a e_b; S symmetric)
        ua, ub = g0 * C_kw[0, a] + g1 * C_kw[1, a], g0 * C_kw[0, b] + g1 * C_kw[1, b]
        Sga, Sgb = wT[b] * S[a, a] + wT[a] * S[b, a], wT[b] * S[a, b] + wT[a] * S[b, b]
        s_m2 = Sga * wT[b] + Sgb * wT[a]
        s_c2 = g0 * (g0 * P[k0, k0] + g1 * P[k0 + 1, k0]) + g1 * (g0 * P[k0, k0 + 1] + g1 * P[k0 + 1, k0 + 1])
        cov = ua * wT[b] + ub * wT[a]
        m0 = wT[a] * wT[b]
        for j in range(K_SIZE):  # A = c'' P_kk
            for m in range(K_SIZE):
                A[j, m] = ddc[i][j][0] * P[k0, k0 + m] + ddc[i][j][1] * P[k0 + 1, k0 + m]
        kk = 0.5 * m0 * m0 * ((A[0, 0] * A[0, 0] + A[0, 1] * A[1, 0]) + (A[1, 0] * A[0, 1] + A[1, 1] * A[1, 1]))
        mixed = 2.0 * c[i] * (ua * Sgb + Sga * ub)
        quad = S[a, a] * S[b, b] + S[a, b] * S[a, b]
        out[i] = (c[i] * c[i] + s_c2) * quad + s_c2 * s_m2 + cov * cov + kk + mixed


@njit(**_JIT)
def pseudo_variance_batch(x, P, w0, nd):
    """``(B, 3)``: ``core.inertia.pseudo_second_order_variance`` of every trial, from the ``omega`` block of ``P`` at
    ``w0`` and its last ``K_SIZE`` rows (``k``); ``nd`` the leader's ``nu'``."""
    B = x.shape[0]
    out = np.empty((B, PSEUDO_ROWS))
    own = (np.empty((VEC, VEC)), np.empty((VEC, VEC)), np.empty((VEC, VEC)), np.empty((K_SIZE, VEC)),
           np.empty((K_SIZE, K_SIZE)))  # fmt: skip
    x, P, ob = borrow((x, P, out))  # (_refs; the scratch kept to the end)
    D, S, T, C_kw, A = borrow(own)
    for b in range(B):
        _pseudo_variance(x[b], P[b], w0, nd, ob[b], D, S, T, C_kw, A)
    keep(own)
    return out


@njit(**_JIT)
def _nonneg(v):
    """``v``, or 0 where round-off of its terms made it negative; NaN stays NaN (``np.maximum(v, 0)``)."""
    return 0.0 if v < 0.0 else v


@njit(**_JIT)
def rate_noise_batch(x, P, w0, nd, dt, Q):
    """``(B, n)``: ``Q (n,)`` with ``dt^2`` times ``core.inertia.rate_second_order_variance`` added to ``omega``'s
    entries, per trial: the pseudo rows' remainder variances ``v_b`` (``_pseudo_variance``, ``P``'s blocks as in
    ``pseudo_variance_batch``) and ``(sum_b |D_ab| sqrt(v_b))^2`` per axis ``a`` of ``L``."""
    B, n = x.shape
    out = np.empty((B, n))
    own = (np.empty(PSEUDO_ROWS), np.empty((VEC, VEC)), np.empty((VEC, VEC)), np.empty((VEC, VEC)),
           np.empty((K_SIZE, VEC)), np.empty((K_SIZE, K_SIZE)))  # fmt: skip
    x, P, Q, ob = borrow((x, P, Q, out))  # (_refs; the scratch kept to the end)
    v, D, S, T, C_kw, A = borrow(own)
    dt2 = dt * dt
    for b in range(B):
        for i in range(n):
            ob[b, i] = Q[i]
        _pseudo_variance(x[b], P[b], w0, nd, v, D, S, T, C_kw, A)  # (D = D(q) of x[b] on return)
        s0, s1, s2 = math.sqrt(_nonneg(v[0])), math.sqrt(_nonneg(v[1])), math.sqrt(_nonneg(v[2]))
        for a in range(VEC):
            r = (abs(D[a, 0]) * s0 + abs(D[a, 1]) * s1) + abs(D[a, 2]) * s2
            ob[b, OMEGA + a] += dt2 * (r * r)
    keep(own)
    return out
