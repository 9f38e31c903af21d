"""Compiled (Numba) twins of the model functions: ``f``, RK4, ``F``, ``Phi``, ``P-``, ``h``, ``H``.

The numpy versions in ``core.dynamics``, ``core.jacobians``, ``core.camera``,
``core.inertia`` and ``core.kalman`` are the readable reference; every kernel here
computes the same equations (their docstrings give them) one trial at a time inside a
loop over the batch, float64, without numpy temporaries, ``nogil`` so that threads run
chunks in parallel, ``cache=True`` so that the compiled code is kept on disk after the
first run. Inputs are batch-first: ``x (B, n)``, ``P (B, n, n)``.

Structure that the kernels use (and the dense numpy code ignores):

- ``F = df/dx`` is zero outside the rows of ``rho, rho_dot, omega, q`` (13) and, there,
  outside the columns ``c = [0..12, k1, k2]`` (15). So ``F^j`` keeps that pattern and
  ``Phi = expm(F dt)`` is the identity except ``Phi[0:13, c] = T`` (13 x 15); the
  covariance predict ``P- = Phi P Phi^T + Q`` is then
  ``P-[a, a] = T P[c, c] T^T``, ``P-[a, r] = T P[c, r]``, ``P-[r, r] = P[r, r]`` (``a = 0..12``,
  ``r`` the rest), ``+ Q``: O(n) work instead of O(n^3).
- The 8 (or 9) rows of feature ``i`` depend only on ``rho, rho_dot, omega, q`` and ``P_i``:
  16 non-zero columns. The 3 pseudo-measurement rows touch ``omega, q, k`` (9 columns).
  ``H`` is therefore returned row-sparse: values ``(B, m, 16)`` and their columns
  ``(m, 16)`` (padding entries have value 0 and column 0).
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from .. import layout
from ..layout import (COMMON, K_SIZE, OMEGA, POINTS, PSEUDO_ROWS, QUAT, QUAT_SIZE, R_K, REDUCED, RHO, RHO_DOT,
                      TRANSLATION, VEC)  # fmt: skip
from ._refs import borrow, keep

NNZ = COMMON + VEC  # non-zero columns of one measurement row: rho, rho_dot, omega, q and one point
H_POINT = COMMON  # a feature row's point columns in the row-sparse H (before them: the state's own columns)
PS_OMEGA, PS_QUAT, PS_K = 0, VEC, VEC + QUAT_SIZE  # a pseudo row's omega, q, k in the row-sparse H
PS_NNZ = PS_K + K_SIZE
Q_END = QUAT + QUAT_SIZE

# core.layout's helpers, inside the kernels
n_points = njit(inline="always", error_model="numpy")(layout.n_points)
n_channels = njit(inline="always", error_model="numpy")(layout.n_channels)
n_measurements = njit(inline="always", error_model="numpy")(layout.n_measurements)

# The measurement model of one step, the same for every trial: the visible features ``vis`` (int64 indices), the
# camera (``baseline``, ``disparity``: whether the disparity channel is measured, ``focal``), whether the inertia
# pseudo rows are measured (``pseudo``) and the leader's ``nu'``, ``nu''`` they read (``nd``, ``ndd``). One argument
# for the kernels (a Numba named tuple: a struct passed by value); the per-trial measured acceleration ``alpha`` goes
# beside it. ``filters.compiled.step_model`` builds it with the types the kernels are compiled for.
StepModel = namedtuple("StepModel", ("vis", "baseline", "disparity", "focal", "pseudo", "nd", "ndd"))

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")


# --- attitude building blocks ------------------------------------------------------


@njit(**_JIT)
def _dcm(q, D):
    """``D(q)`` of the normalized quaternion (homogeneous form, as ``quaternion.dcm``)."""
    q0, q1, q2, q3 = q[0], q[1], q[2], q[3]
    n2 = q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3
    r = 1.0 / n2  # (products by 1 / |q|^2: one division, not nine)
    D[0, 0] = (q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3) * r
    D[0, 1] = 2.0 * (q1 * q2 - q0 * q3) * r
    D[0, 2] = 2.0 * (q1 * q3 + q0 * q2) * r
    D[1, 0] = 2.0 * (q1 * q2 + q0 * q3) * r
    D[1, 1] = (q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3) * r
    D[1, 2] = 2.0 * (q2 * q3 - q0 * q1) * r
    D[2, 0] = 2.0 * (q1 * q3 - q0 * q2) * r
    D[2, 1] = 2.0 * (q2 * q3 + q0 * q1) * r
    D[2, 2] = (q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3) * r
    return n2


@njit(**_JIT)
def _dcm_derivative(q, D, dD):
    """``D`` and ``dD[j] = dD/dq_j = (dA/dq_j - 2 q_j D) / |q|^2`` (``jacobians.dcm_derivative``)."""
    n2 = _dcm(q, D)
    q0, q1, q2, q3 = q[0], q[1], q[2], q[3]
    dA = dD  # dA/dq_j of the homogeneous numerator A(q) (jacobians._dA_dq_explicit), in dD's memory, then
    # dD = (2 dA - 2 q_j D) / |q|^2 in place
    dA[0, 0, 0], dA[0, 0, 1], dA[0, 0, 2] = q0, -q3, q2
    dA[0, 1, 0], dA[0, 1, 1], dA[0, 1, 2] = q3, q0, -q1
    dA[0, 2, 0], dA[0, 2, 1], dA[0, 2, 2] = -q2, q1, q0
    dA[1, 0, 0], dA[1, 0, 1], dA[1, 0, 2] = q1, q2, q3
    dA[1, 1, 0], dA[1, 1, 1], dA[1, 1, 2] = q2, -q1, -q0
    dA[1, 2, 0], dA[1, 2, 1], dA[1, 2, 2] = q3, q0, -q1
    dA[2, 0, 0], dA[2, 0, 1], dA[2, 0, 2] = -q2, q1, q0
    dA[2, 1, 0], dA[2, 1, 1], dA[2, 1, 2] = q1, q2, q3
    dA[2, 2, 0], dA[2, 2, 1], dA[2, 2, 2] = -q0, q3, -q2
    dA[3, 0, 0], dA[3, 0, 1], dA[3, 0, 2] = -q3, -q0, q1
    dA[3, 1, 0], dA[3, 1, 1], dA[3, 1, 2] = q0, -q3, q2
    dA[3, 2, 0], dA[3, 2, 1], dA[3, 2, 2] = q1, q2, q3
    s = 1.0 / n2  # (one division, not 36)
    for j in range(4):
        for r in range(3):
            for c in range(3):
                dD[j, r, c] = (2.0 * dA[j, r, c] - 2.0 * q[j] * D[r, c]) * s


@njit(**_JIT)
def _euler_terms(wT, k1, k2, g, G, dgdk):
    """``g = -I^-1 (w_T x I w_T) = c * p``, ``G = dg/dw_T``, ``dg/dk`` (``jacobians._euler_terms``)."""
    J1 = math.exp(k1)
    J3 = math.exp(-k2)
    c0, c1, c2 = (1.0 - J3) / J1, J3 - J1, (J1 - 1.0) / J3
    w1, w2, w3 = wT[0], wT[1], wT[2]
    p0, p1, p2 = w2 * w3, w3 * w1, w1 * w2
    g[0], g[1], g[2] = c0 * p0, c1 * p1, c2 * p2
    G[0, 0], G[0, 1], G[0, 2] = 0.0, c0 * w3, c0 * w2
    G[1, 0], G[1, 1], G[1, 2] = c1 * w3, 0.0, c1 * w1
    G[2, 0], G[2, 1], G[2, 2] = c2 * w2, c2 * w1, 0.0
    dgdk[0, 0], dgdk[1, 0], dgdk[2, 0] = -p0 * (1.0 - J3) / J1, -p1 * J1, p2 * J1 / J3
    dgdk[0, 1], dgdk[1, 1], dgdk[2, 1] = p0 * J3 / J1, -p1 * J3, p2 * (J1 - 1.0) / J3


# --- process model --------------------------------------------------------------


@njit(**_JIT)
def _f(x, rL, nd, ndd, mu, out, D):
    """``out = f(x)`` for one trial (``dynamics.f``); ``D`` is 3 x 3 scratch."""
    n = x.shape[0]
    X, Y, Z = x[RHO], x[RHO + 1], x[RHO + 2]
    vx, vy = x[RHO_DOT], x[RHO_DOT + 1]
    R3 = ((rL + X) ** 2 + Y * Y + Z * Z) ** 1.5
    out[RHO], out[RHO + 1], out[RHO + 2] = x[RHO_DOT], x[RHO_DOT + 1], x[RHO_DOT + 2]
    out[RHO_DOT] = 2.0 * nd * vy + ndd * Y + nd * nd * X - mu * (rL + X) / R3 + mu / (rL * rL)
    out[RHO_DOT + 1] = -2.0 * nd * vx - ndd * X + nd * nd * Y - mu * Y / R3
    out[RHO_DOT + 2] = -mu * Z / R3
    _dcm(x[QUAT:Q_END], D)
    w0, w1, w2 = x[OMEGA], x[OMEGA + 1], x[OMEGA + 2]
    W2 = w2 + nd
    # w_T = D^T (w + w_L); w_rel_T = D^T w
    t0 = D[0, 0] * w0 + D[1, 0] * w1 + D[2, 0] * W2
    t1 = D[0, 1] * w0 + D[1, 1] * w1 + D[2, 1] * W2
    t2 = D[0, 2] * w0 + D[1, 2] * w1 + D[2, 2] * W2
    r0 = D[0, 0] * w0 + D[1, 0] * w1 + D[2, 0] * w2
    r1 = D[0, 1] * w0 + D[1, 1] * w1 + D[2, 1] * w2
    r2 = D[0, 2] * w0 + D[1, 2] * w1 + D[2, 2] * w2
    J0 = math.exp(x[n - K_SIZE])
    J2 = math.exp(-x[n - K_SIZE + 1])
    # Euler: w_T' = -(w_T x I w_T) / I
    e0 = -(t1 * (J2 * t2) - t2 * t1) / J0
    e1 = -(t2 * (J0 * t0) - t0 * (J2 * t2))
    e2 = -(t0 * t1 - t1 * (J0 * t0)) / J2
    # w' = D w_T' - w_L x w - w_L'
    out[OMEGA] = D[0, 0] * e0 + D[0, 1] * e1 + D[0, 2] * e2 + nd * w1
    out[OMEGA + 1] = D[1, 0] * e0 + D[1, 1] * e1 + D[1, 2] * e2 - nd * w0
    out[OMEGA + 2] = D[2, 0] * e0 + D[2, 1] * e1 + D[2, 2] * e2 - ndd
    q0, q1, q2, q3 = x[QUAT], x[QUAT + 1], x[QUAT + 2], x[QUAT + 3]
    out[QUAT] = 0.5 * (-q1 * r0 - q2 * r1 - q3 * r2)
    out[QUAT + 1] = 0.5 * (q0 * r0 + q2 * r2 - q3 * r1)
    out[QUAT + 2] = 0.5 * (q0 * r1 - q1 * r2 + q3 * r0)
    out[QUAT + 3] = 0.5 * (q0 * r2 + q1 * r1 - q2 * r0)
    for i in range(COMMON, n):
        out[i] = 0.0


@njit(**_JIT)
def f_batch(x, rL, nd, ndd, mu):
    """``f`` of every trial, ``(B, n)``."""
    B, n = x.shape
    out = np.empty((B, n))
    D = np.empty((3, 3))
    for b in range(B):
        _f(x[b], rL, nd, ndd, mu, out[b], D)
    return out


@njit(**_JIT)
def propagate_batch(x, rL, nd, ndd, h, mu, substeps, renormalize):
    """RK4 of ``f`` (``dynamics.propagate``): ``substeps`` steps of ``h``.

    ``rL, nd, ndd (2 substeps + 1,)`` are the leader's kinematics at ``t + i h / 2``.
    With ``renormalize`` the quaternion of the result is normalized (``relnav.renormalize``).
    """
    B, n = x.shape
    out = np.empty((B, n))
    y = np.empty(n)
    yt = np.empty(n)
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    D = np.empty((3, 3))
    own = (y, yt, k1, k2, k3, k4, D)  # borrowed below (_refs), kept to the end
    y, yt, k1, k2, k3, k4, D = borrow(own)
    for b in range(B):
        for i in range(n):
            y[i] = x[b, i]
        for j in range(substeps):
            s = 2 * j
            _f(y, rL[s], nd[s], ndd[s], mu, k1, D)
            for i in range(n):
                yt[i] = y[i] + 0.5 * h * k1[i]
            _f(yt, rL[s + 1], nd[s + 1], ndd[s + 1], mu, k2, D)
            for i in range(n):
                yt[i] = y[i] + 0.5 * h * k2[i]
            _f(yt, rL[s + 1], nd[s + 1], ndd[s + 1], mu, k3, D)
            for i in range(n):
                yt[i] = y[i] + h * k3[i]
            _f(yt, rL[s + 2], nd[s + 2], ndd[s + 2], mu, k4, D)
            for i in range(n):
                y[i] = y[i] + (h / 6.0) * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
        if renormalize:
            qn = math.sqrt(y[QUAT] * y[QUAT] + y[QUAT + 1] * y[QUAT + 1] + y[QUAT + 2] * y[QUAT + 2]
                           + y[QUAT + 3] * y[QUAT + 3])  # fmt: skip
            for i in range(QUAT, Q_END):
                y[i] = y[i] / qn
        for i in range(n):
            out[b, i] = y[i]
    keep(own)
    return out


_F_SCRATCH = 42  # _F_reduced's W, w_T, v, g, G, dg/dk, D G, dD_j^T W, dD_j^T w


@njit(**_JIT)
def _F_reduced(x, rL, nd, ndd, mu, Fr, D, dD, ws):
    """The non-zero block of ``F = df/dx`` (``jacobians.F``) on the columns ``c = [0..12, k1, k2]``.

    ``Fr (13, 15)``: rows ``rho, rho_dot, omega, q``; columns 0-12 and 13-14 (``k``); ``ws``: scratch of
    ``_F_SCRATCH`` floats.
    """
    n = x.shape[0]
    for i in range(COMMON):
        for j in range(REDUCED):
            Fr[i, j] = 0.0
    Fr[RHO, RHO_DOT] = Fr[RHO + 1, RHO_DOT + 1] = Fr[RHO + 2, RHO_DOT + 2] = 1.0
    s0, s1, s2 = rL + x[RHO], x[RHO + 1], x[RHO + 2]
    R2 = s0 * s0 + s1 * s1 + s2 * s2
    cg = -mu / R2**1.5
    sv = (s0, s1, s2)
    for i in range(3):
        for j in range(3):
            Fr[RHO_DOT + i, RHO + j] = cg * ((1.0 if i == j else 0.0) - 3.0 * sv[i] * sv[j] / R2)
    Fr[RHO_DOT, RHO] += nd * nd
    Fr[RHO_DOT + 1, RHO + 1] += nd * nd
    Fr[RHO_DOT, RHO + 1] += ndd
    Fr[RHO_DOT + 1, RHO] -= ndd
    Fr[RHO_DOT, RHO_DOT + 1] = 2.0 * nd
    Fr[RHO_DOT + 1, RHO_DOT] = -2.0 * nd
    _dcm_derivative(x[QUAT:Q_END], D, dD)
    w = x[OMEGA : OMEGA + VEC]
    W = ws[0:3]
    W[0], W[1], W[2] = w[0], w[1], w[2] + nd
    wT = ws[3:6]
    v = ws[6:9]
    for i in range(3):
        wT[i] = D[0, i] * W[0] + D[1, i] * W[1] + D[2, i] * W[2]
        v[i] = D[0, i] * w[0] + D[1, i] * w[1] + D[2, i] * w[2]
    g = ws[9:12]
    G = ws[12:21].reshape((3, 3))
    dgdk = ws[21:27].reshape((3, 2))
    _euler_terms(wT, x[n - K_SIZE], x[n - K_SIZE + 1], g, G, dgdk)
    DG = ws[27:36].reshape((3, 3))
    for i in range(3):
        for j in range(3):
            DG[i, j] = D[i, 0] * G[0, j] + D[i, 1] * G[1, j] + D[i, 2] * G[2, j]
    for i in range(3):
        for j in range(3):
            Fr[OMEGA + i, OMEGA + j] = DG[i, 0] * D[j, 0] + DG[i, 1] * D[j, 1] + DG[i, 2] * D[j, 2]
    Fr[OMEGA, OMEGA + 1] += nd
    Fr[OMEGA + 1, OMEGA] -= nd
    dW = ws[36:39]
    dw = ws[39:42]
    for j in range(4):
        for i in range(3):  # dD_j^T W and dD_j^T w
            dW[i] = dD[j, 0, i] * W[0] + dD[j, 1, i] * W[1] + dD[j, 2, i] * W[2]
            dw[i] = dD[j, 0, i] * w[0] + dD[j, 1, i] * w[1] + dD[j, 2, i] * w[2]
        for i in range(3):
            Fr[OMEGA + i, QUAT + j] = (dD[j, i, 0] * g[0] + dD[j, i, 1] * g[1] + dD[j, i, 2] * g[2]
                                + DG[i, 0] * dW[0] + DG[i, 1] * dW[1] + DG[i, 2] * dW[2])  # fmt: skip
        # q <- q_j: 1/2 (M(D^T w)[:, j] + Q(q) dD_j^T w)
        q0, q1, q2, q3 = x[QUAT], x[QUAT + 1], x[QUAT + 2], x[QUAT + 3]
        Fr[QUAT, QUAT + j] = 0.5 * (-q1 * dw[0] - q2 * dw[1] - q3 * dw[2])
        Fr[QUAT + 1, QUAT + j] = 0.5 * (q0 * dw[0] - q3 * dw[1] + q2 * dw[2])
        Fr[QUAT + 2, QUAT + j] = 0.5 * (q3 * dw[0] + q0 * dw[1] - q1 * dw[2])
        Fr[QUAT + 3, QUAT + j] = 0.5 * (-q2 * dw[0] + q1 * dw[1] + q0 * dw[2])
    # M(v) = d(q (x) [0, v])/dq
    Fr[QUAT, QUAT + 1] += -0.5 * v[0]
    Fr[QUAT, QUAT + 2] += -0.5 * v[1]
    Fr[QUAT, QUAT + 3] += -0.5 * v[2]
    Fr[QUAT + 1, QUAT] += 0.5 * v[0]
    Fr[QUAT + 1, QUAT + 2] += 0.5 * v[2]
    Fr[QUAT + 1, QUAT + 3] += -0.5 * v[1]
    Fr[QUAT + 2, QUAT] += 0.5 * v[1]
    Fr[QUAT + 2, QUAT + 1] += -0.5 * v[2]
    Fr[QUAT + 2, QUAT + 3] += 0.5 * v[0]
    Fr[QUAT + 3, QUAT] += 0.5 * v[2]
    Fr[QUAT + 3, QUAT + 1] += 0.5 * v[1]
    Fr[QUAT + 3, QUAT + 2] += -0.5 * v[0]
    for i in range(3):
        for j in range(2):
            Fr[OMEGA + i, R_K + j] = D[i, 0] * dgdk[0, j] + D[i, 1] * dgdk[1, j] + D[i, 2] * dgdk[2, j]
    # q <- w: 1/2 Q(q) D^T
    q0, q1, q2, q3 = x[QUAT], x[QUAT + 1], x[QUAT + 2], x[QUAT + 3]
    for j in range(3):
        Fr[QUAT, OMEGA + j] = 0.5 * (-q1 * D[j, 0] - q2 * D[j, 1] - q3 * D[j, 2])
        Fr[QUAT + 1, OMEGA + j] = 0.5 * (q0 * D[j, 0] - q3 * D[j, 1] + q2 * D[j, 2])
        Fr[QUAT + 2, OMEGA + j] = 0.5 * (q3 * D[j, 0] + q0 * D[j, 1] - q1 * D[j, 2])
        Fr[QUAT + 3, OMEGA + j] = 0.5 * (-q2 * D[j, 0] + q1 * D[j, 1] + q0 * D[j, 2])


@njit(**_JIT)
def F_reduced_batch(x, rL, nd, ndd, mu):
    """``F[:, 0:13, c]`` (``B, 13, 15``), ``c = [0..12, n-2, n-1]``: the only non-zero block of ``F``."""
    B = x.shape[0]
    out = np.empty((B, COMMON, REDUCED))
    D = np.empty((3, 3))
    dD = np.empty((4, 3, 3))
    ws = np.empty(_F_SCRATCH)
    own = (D, dD, ws)  # borrowed below (_refs), kept to the end
    xb, ob, D, dD, ws = borrow((x, out, D, dD, ws))
    for b in range(B):
        _F_reduced(xb[b], rL, nd, ndd, mu, ob[b], D, dD, ws)
    keep(own)
    return out


@njit(**_JIT)
def F_batch(x, rL, nd, ndd, mu):
    """Dense ``F = df/dx`` (``B, n, n``), for tests and the numpy-shaped API."""
    B, n = x.shape
    Fr = F_reduced_batch(x, rL, nd, ndd, mu)
    out = np.zeros((B, n, n))
    for b in range(B):
        for i in range(COMMON):
            for j in range(COMMON):
                out[b, i, j] = Fr[b, i, j]
            for j in range(K_SIZE):
                out[b, i, n - K_SIZE + j] = Fr[b, i, R_K + j]
    return out


@njit(**_JIT)
def _taylor_reduced(Fr, dt, order, T, A, tmp):
    """``T = Phi[0:13, c]`` of ``Phi = sum_{j<=order} (F dt)^j / j!`` by Horner (``kalman.transition_matrix``).

    On the 15 columns ``c`` the reduced ``F`` is the square ``[[Fr], [0]]`` (15 x 15), and block diagonal
    (``_F_reduced``): the translation's rows (``rho, rho_dot``: 0-5) see its columns 0-5 only, the rotation's rows
    (``omega, q``: 6-12) the columns 6-14 only (``omega, q, k``; the rows of ``k``, 13-14, are zero). So are its
    powers: each Horner product runs on the two blocks (6 x 6 and 7 x 9 times 9 x 9, a quarter of the full
    product's flops, without a BLAS call's cost on such small blocks) and ``T``'s other entries stay zero. By rows
    of ``T`` (contiguous, vectorized), each entry's sum in the order of its terms.
    """
    # A = [[Fr dt], [0]] (15 x 15): its rows 0-12 (13, 14 are zero, never read); Phi15 = I + A/order, I + A Phi15 / j
    r = 1.0 / order
    for i in range(COMMON):
        for j in range(REDUCED):
            A[i, j] = Fr[i, j] * dt
            T[i, j] = (1.0 if i == j else 0.0) + A[i, j] * r
    for i in range(COMMON, REDUCED):
        for j in range(REDUCED):
            T[i, j] = 1.0 if i == j else 0.0
    for jj in range(order - 1, 0, -1):
        # tmp = A[:13] T on the two blocks (rows 13, 14 of A are zero); constant bounds: unrolled
        # (A's exact zeros skipped, as predict_covariance_batch skips T's: rho's rows are [0, I dt], q's rows do not
        # see k; a finite T's sums are the same numbers without their exact-zero terms)
        for i in range(TRANSLATION):
            for j in range(TRANSLATION):
                tmp[i, j] = 0.0
            for k in range(TRANSLATION):
                a = A[i, k]
                if a != 0.0:
                    for j in range(TRANSLATION):
                        tmp[i, j] += a * T[k, j]
        for i in range(TRANSLATION, COMMON):
            for j in range(TRANSLATION, REDUCED):
                tmp[i, j] = 0.0
            for k in range(TRANSLATION, REDUCED):
                a = A[i, k]
                if a != 0.0:
                    for j in range(TRANSLATION, REDUCED):
                        tmp[i, j] += a * T[k, j]
        r = 1.0 / jj  # (a product by 1/j, not 63 + 36 divisions: exact for j = 1, 2, 4; within an ulp for j = 3)
        for i in range(TRANSLATION):
            for j in range(TRANSLATION):
                T[i, j] = (1.0 if i == j else 0.0) + tmp[i, j] * r
        for i in range(TRANSLATION, COMMON):
            for j in range(TRANSLATION, REDUCED):
                T[i, j] = (1.0 if i == j else 0.0) + tmp[i, j] * r
        # rows 13, 14 stay the identity (A is zero there); the entries off the blocks stay zero


@njit(**_JIT)
def transition_reduced_batch(Fr, dt, order):
    """``Phi[:, 0:13, c]`` (``B, 13, 15``) from ``F_reduced_batch``: the rest of ``Phi`` is the identity."""
    B = Fr.shape[0]
    out = np.empty((B, COMMON, REDUCED))
    T = np.empty((REDUCED, REDUCED))
    A = np.empty((COMMON, REDUCED))
    tmp = np.empty((COMMON, REDUCED))
    own = (T, A, tmp)  # borrowed below (_refs), kept to the end
    Fb, T, A, tmp = borrow((Fr, T, A, tmp))
    for b in range(B):
        _taylor_reduced(Fb[b], dt, order, T, A, tmp)
        for i in range(COMMON):
            for j in range(REDUCED):
                out[b, i, j] = T[i, j]
    keep(own)
    return out


@njit(**_JIT)
def predict_state_batch(x, rL, nd, ndd, h, mu, substeps, dt, order):
    """``(x-, Phi[:, 0:13, c])``: ``propagate_batch`` (quaternion renormalized) and ``transition_reduced_batch``
    of ``F_reduced_batch`` at ``x`` (the leader at ``rL[0], nd[0], ndd[0]``), in one call."""
    Fr = F_reduced_batch(x, rL[0], nd[0], ndd[0], mu)
    return propagate_batch(x, rL, nd, ndd, h, mu, substeps, True), transition_reduced_batch(Fr, dt, order)


@njit(**_JIT)
def predict_covariance_batch(P, T, Q):
    """``P- = Phi P Phi^T + Q``, symmetrized, for ``Phi`` = identity except ``Phi[0:13, c] = T``.

    ``Q (B, n)`` the diagonal of the process noise (``kalman.predict_covariance``).
    """
    B, n, _ = P.shape
    out = np.empty((B, n, n))
    cols = np.empty(REDUCED, np.int64)
    for j in range(COMMON):
        cols[j] = j
    for j in range(K_SIZE):
        cols[R_K + j] = n - K_SIZE + j
    TP = np.empty((COMMON, n))  # T P[c, :]
    Tt = np.empty((REDUCED, COMMON))  # T^T
    acc = np.empty(COMMON)
    for b in range(B):
        # T P[c, :] by scaled rows of P (contiguous, vectorized), not by dot products down its columns
        # (the zeros of T (rho, rho_dot do not see the attitude) are skipped: a finite P's sums are
        # the same numbers without their exact-zero terms)
        for i in range(COMMON):
            for j in range(n):
                TP[i, j] = 0.0
            for l in range(REDUCED):
                t = T[b, i, l]
                if t != 0.0:
                    cl = cols[l]  # (P's row read in place: a view's reference counting would cost more than the sums)
                    for j in range(n):
                        TP[i, j] += t * P[b, cl, j]
            for l in range(REDUCED):
                Tt[l, i] = T[b, i, l]
        for i in range(n):
            for j in range(n):
                out[b, i, j] = P[b, i, j]
        # rows/cols 0..12 against the rest: (T P)[a, r]; against themselves: (T P)[a, c] T^T
        for i in range(COMMON):
            for j in range(COMMON, n):
                out[b, i, j] = TP[i, j]
                out[b, j, i] = TP[i, j]
            # acc = (T P)[i, c] T^T by T's blocks (_taylor_reduced): the translation's rows 0-5 have non-zeros in the
            # columns 0-5 only, the rotation's 6-12 in the columns 6-14: the terms left out are exact zeros
            for j in range(COMMON):
                acc[j] = 0.0
            for l in range(TRANSLATION):
                t = TP[i, l]  # cols[l] = l
                for j in range(TRANSLATION):
                    acc[j] += t * Tt[l, j]
            for l in range(TRANSLATION, REDUCED):
                t = TP[i, cols[l]]
                for j in range(TRANSLATION, COMMON):
                    acc[j] += t * Tt[l, j]
            for j in range(i, COMMON):
                out[b, i, j] = acc[j]
                out[b, j, i] = acc[j]
        # k rows/cols (n-2, n-1) are not in 0..12: they took (T P)[a, k] above
        for i in range(n):
            out[b, i, i] += Q[b, i]
    return out


# --- measurement model ----------------------------------------------------------


_MEASURE_SCRATCH = 84  # _feature_rows' J, K0 (a 12 x 7 matrix); _pseudo_rows' W, a, wT, g, G, dg/dk (27)


@njit(**_JIT)
def _feature_rows(x, vis, baseline, disparity, focal, D, dD, compute_jac, hx, Hval, ws):
    """``h`` and the 16 non-zero Jacobian columns of every visible feature: those of feature ``vis[f]`` in the rows
    ``f C .. f C + C - 1`` of ``hx`` and ``Hval`` (``C`` channels).

    Columns 0-12 are ``rho, rho_dot, omega, q``, 13-15 the point ``P_i`` (``jacobians.H_features_compact``).
    ``ws``: a 12 x 7 scratch matrix (no allocation per feature): ``J (9 x 6)`` in its top left, ``K0 (3 x 7)`` in
    its last rows. The rows, the point, ``r`` and ``w`` are indexed in place or held as scalars, not as array
    views: a view costs an atomic increment and decrement of its reference count, which between the stores
    of these rows cost more than their arithmetic. The features are looped over here, not by the caller: each
    array a compiled function takes costs the same two operations per call.
    """
    C = n_channels(disparity)
    for f in range(vis.shape[0]):
        i = vis[f]
        o = f * C
        p0 = POINTS + VEC * i
        P0, P1, P2 = x[p0], x[p0 + 1], x[p0 + 2]
        w0, w1, w2 = x[OMEGA], x[OMEGA + 1], x[OMEGA + 2]
        r0 = D[0, 0] * P0 + D[0, 1] * P1 + D[0, 2] * P2
        r1 = D[1, 0] * P0 + D[1, 1] * P1 + D[1, 2] * P2
        r2 = D[2, 0] * P0 + D[2, 1] * P1 + D[2, 2] * P2
        X, Y, Z = x[RHO] + r0, x[RHO + 1] + r1, x[RHO + 2] + r2
        vX = x[RHO_DOT] + (w1 * r2 - w2 * r1)
        vY = x[RHO_DOT + 1] + (w2 * r0 - w0 * r2)
        vZ = x[RHO_DOT + 2] + (w0 * r1 - w1 * r0)
        iy = 1.0 / Y
        xl = X - baseline
        u_r, v_r, u_l = X * iy, Z * iy, xl * iy
        hx[o] = u_r * focal
        hx[o + 1] = v_r * focal
        hx[o + 2] = u_l * focal
        hx[o + 3] = v_r * focal
        hx[o + 4] = (vX * Y - X * vY) * iy * iy * focal
        hx[o + 5] = (vZ * Y - Z * vY) * iy * iy * focal
        hx[o + 6] = (vX * Y - xl * vY) * iy * iy * focal
        hx[o + 7] = hx[o + 5]
        if disparity:
            hx[o + 8] = (u_l - u_r) * focal
        if not compute_jac:
            continue
        iy2 = iy * iy
        # J = ws[:9, :6] = [dh/d rho_i | dh/d rho_dot_i] (jacobians._projection_gradients)
        for c in range(9):
            for j in range(6):
                ws[c, j] = 0.0
        ws[0, 0] = ws[2, 0] = iy
        ws[0, 1] = -X * iy2
        ws[2, 1] = -xl * iy2
        ws[1, 1] = ws[3, 1] = -Z * iy2
        ws[1, 2] = ws[3, 2] = iy
        for a in range(4):
            for c in range(3):
                ws[4 + a, 3 + c] = ws[a, c]
        vyy = 2.0 * vY * iy2 * iy
        vy2 = -vY * iy2
        ws[4, 0] = ws[6, 0] = vy2
        ws[4, 1] = -vX * iy2 + X * vyy
        ws[6, 1] = -vX * iy2 + xl * vyy
        ws[5, 1] = ws[7, 1] = -vZ * iy2 + Z * vyy
        ws[5, 2] = ws[7, 2] = vy2
        if disparity:
            ws[8, 1] = baseline * iy2
        # K0 = ws[9:12] = [dr/dq_j (4 cols) | D (3 cols)] (3 x 7)
        for j in range(4):
            for a in range(3):
                ws[9 + a, j] = dD[j, a, 0] * P0 + dD[j, a, 1] * P1 + dD[j, a, 2] * P2
        for a in range(3):
            for c in range(3):
                ws[9 + a, 4 + c] = D[a, c]
        for c in range(C):
            jp0, jp1, jp2 = ws[c, 0], ws[c, 1], ws[c, 2]
            jv0, jv1, jv2 = ws[c, 3], ws[c, 4], ws[c, 5]
            rr = o + c
            Hval[rr, RHO], Hval[rr, RHO + 1], Hval[rr, RHO + 2] = jp0 * focal, jp1 * focal, jp2 * focal
            Hval[rr, RHO_DOT], Hval[rr, RHO_DOT + 1], Hval[rr, RHO_DOT + 2] = jv0 * focal, jv1 * focal, jv2 * focal
            # d/dw = -Jv [r x] = r x Jv
            Hval[rr, OMEGA] = (r1 * jv2 - r2 * jv1) * focal
            Hval[rr, OMEGA + 1] = (r2 * jv0 - r0 * jv2) * focal
            Hval[rr, OMEGA + 2] = (r0 * jv1 - r1 * jv0) * focal
            # d/d[q, P_i] = (Jp + Jv [w x]) K0 = (Jp + Jv x w) K0
            e0 = jp0 + (jv1 * w2 - jv2 * w1)
            e1 = jp1 + (jv2 * w0 - jv0 * w2)
            e2 = jp2 + (jv0 * w1 - jv1 * w0)
            for j in range(QUAT_SIZE + VEC):  # q, then the point (H_POINT = Q_END)
                Hval[rr, QUAT + j] = (e0 * ws[9, j] + e1 * ws[10, j] + e2 * ws[11, j]) * focal


@njit(**_JIT)
def _pseudo_rows(x, alpha, nd, ndd, D, dD, compute_jac, hrow, Hval, ws):
    """Euler residual ``h_pseudo`` (3,) and its 9 non-zero Jacobian columns ``[omega, q, k]`` (``Hval (3, 16)``);
    ``ws``: scratch of ``_MEASURE_SCRATCH`` floats."""
    n = x.shape[0]
    w0, w1, w2 = x[OMEGA], x[OMEGA + 1], x[OMEGA + 2]
    W = ws[0:3]
    W[0], W[1], W[2] = w0, w1, w2 + nd
    a = ws[3:6]
    a[0] = alpha[0] - nd * w1
    a[1] = alpha[1] + nd * w0
    a[2] = alpha[2] + ndd
    wT = ws[6:9]
    for i in range(3):
        wT[i] = D[0, i] * W[0] + D[1, i] * W[1] + D[2, i] * W[2]
    J0 = math.exp(x[n - K_SIZE])
    J2 = math.exp(-x[n - K_SIZE + 1])
    Iw0, Iw1, Iw2 = J0 * wT[0], wT[1], J2 * wT[2]
    gy0 = (wT[1] * Iw2 - wT[2] * Iw1) / J0
    gy1 = wT[2] * Iw0 - wT[0] * Iw2
    gy2 = (wT[0] * Iw1 - wT[1] * Iw0) / J2
    hrow[0] = D[0, 0] * a[0] + D[1, 0] * a[1] + D[2, 0] * a[2] + gy0
    hrow[1] = D[0, 1] * a[0] + D[1, 1] * a[1] + D[2, 1] * a[2] + gy1
    hrow[2] = D[0, 2] * a[0] + D[1, 2] * a[1] + D[2, 2] * a[2] + gy2
    if not compute_jac:
        return
    g = ws[9:12]
    G = ws[12:21].reshape((3, 3))
    dgdk = ws[21:27].reshape((3, 2))
    _euler_terms(wT, x[n - K_SIZE], x[n - K_SIZE + 1], g, G, dgdk)
    for i in range(3):
        for c in range(NNZ):
            Hval[i, c] = 0.0
        # dh/dw = -G D^T + nd [D^T e_y, -D^T e_x, 0]
        for j in range(3):
            Hval[i, PS_OMEGA + j] = -(G[i, 0] * D[j, 0] + G[i, 1] * D[j, 1] + G[i, 2] * D[j, 2])
        Hval[i, PS_OMEGA] += nd * D[1, i]
        Hval[i, PS_OMEGA + 1] -= nd * D[0, i]
    for j in range(4):
        for i in range(3):
            da = dD[j, 0, i] * a[0] + dD[j, 1, i] * a[1] + dD[j, 2, i] * a[2]
            s = 0.0
            for l in range(3):
                s += G[i, l] * (dD[j, 0, l] * W[0] + dD[j, 1, l] * W[1] + dD[j, 2, l] * W[2])
            Hval[i, PS_QUAT + j] = da - s
    for i in range(3):
        Hval[i, PS_K] = -dgdk[i, 0]
        Hval[i, PS_K + 1] = -dgdk[i, 1]


def row_columns(vis, channels, before, point0, after, pseudo_cols, pseudo):
    """Column indices ``(m, 16)`` of a row-sparse ``H``: each row of visible feature ``f`` holds the
    columns ``before``, then its point's 3 (``point0 + 3 vis[f]``), then ``after``; the 3 pseudo rows
    hold ``pseudo_cols``; the rest is padding (column 0, value 0).

    Plain numpy (called from Python once per visibility pattern: a Numba kernel here only cost
    its load at start-up)."""
    vis = np.asarray(vis, dtype=np.int64)
    nf = vis.size * channels
    cols = np.zeros((nf + (PSEUDO_ROWS if pseudo else 0), NNZ), np.int64)
    nb, na = len(before), len(after)
    cols[:nf, :nb] = before
    cols[:nf, nb : nb + 3] = point0 + 3 * np.repeat(vis, channels)[:, None] + np.arange(3)
    cols[:nf, nb + 3 : nb + 3 + na] = after
    if pseudo:
        cols[nf:, : len(pseudo_cols)] = pseudo_cols
    return cols


def measurement_columns(n, vis, channels, pseudo):
    """Column indices ``(m, 16)`` of the row-sparse ``H`` of ``measure_batch``: a feature's rows see
    ``rho, rho_dot, omega, q`` and its point, the pseudo rows ``omega, q, k``."""
    k = np.arange(n - K_SIZE, n)
    return row_columns(vis, channels, np.arange(COMMON), POINTS, np.arange(0),
                       np.concatenate((np.arange(OMEGA, Q_END), k)), pseudo)  # fmt: skip


@njit(**_JIT)
def _measure_one(x, model, alpha, compute_jac, hx, Hval, D, dD):
    """``h`` and row-sparse ``H`` of one trial (``relnav.measurement_model``); ``model``: a ``StepModel``."""
    _dcm_derivative(x[QUAT:Q_END], D, dD)
    nf = n_measurements(model.vis.shape[0], model.disparity, False)  # the features' rows; then the pseudo rows
    own = np.empty((12, 7))  # the rows' scratch: one allocation per call, not per feature
    ws = borrow(own)  # (_refs; kept to the end)
    _feature_rows(x, model.vis, model.baseline, model.disparity, model.focal, D, dD, compute_jac, hx, Hval, ws)
    if model.pseudo:
        _pseudo_rows(x, alpha, model.nd, model.ndd, D, dD, compute_jac, hx[nf : nf + PSEUDO_ROWS],
                     Hval[nf : nf + PSEUDO_ROWS], ws.ravel())  # fmt: skip
    keep(own)


@njit(**_JIT)
def measure_batch(x, model, alpha, compute_jac):
    """``h (B, m)`` and the values ``(B, m, 16)`` of the row-sparse ``H`` (columns: ``measurement_columns``).

    Rows (``core.layout.n_measurements``): per visible feature ``model.vis`` its 8 (9) channels, then the 3 pseudo
    rows with the per-trial measured acceleration ``alpha (B, 3)``.
    """
    B, n = x.shape
    m = n_measurements(model.vis.shape[0], model.disparity, model.pseudo)
    hx = np.empty((B, m))
    Hval = np.zeros((B, m, NNZ))
    D = np.empty((3, 3))
    dD = np.empty((4, 3, 3))
    for b in range(B):
        _measure_one(x[b], model, alpha[b], compute_jac, hx[b], Hval[b], D, dD)
    return hx, Hval


@njit(**_JIT)
def measure_h_batch(x, model, alpha):
    """``h (B, m)`` of ``measure_batch`` alone (no ``H``: one scratch row block, not ``B x m x 16`` values), for
    the sigma points of the UKF (``2 n + 1`` states per trial)."""
    B, n = x.shape
    m = n_measurements(model.vis.shape[0], model.disparity, model.pseudo)
    hx = np.empty((B, m))
    Hval = np.zeros((m, NNZ))
    D = np.empty((3, 3))
    dD = np.empty((4, 3, 3))
    for b in range(B):
        _measure_one(x[b], model, alpha[b], False, hx[b], Hval, D, dD)
    return hx


@njit(**_JIT)
def _dense_batch(Hval, cols, n):
    """``dense``: each row's values added at their columns, in the order of the row's entries."""
    B, m, k = Hval.shape
    out = np.zeros((B, m, n))
    for b in range(B):
        for r in range(m):
            for j in range(k):
                out[b, r, cols[r, j]] += Hval[b, r, j]
    return out


def dense(Hval: np.ndarray, cols: np.ndarray, n: int) -> np.ndarray:
    """Dense ``(B, m, n)`` from the row-sparse ``H`` (duplicate padding columns carry value 0: the values are added,
    as ``np.add.at`` would, in a compiled loop: ``add.at`` is slow on small arrays)."""
    return _dense_batch(np.ascontiguousarray(Hval, dtype=float), np.ascontiguousarray(cols, dtype=np.int64), int(n))


def dense_transition(T: np.ndarray, n: int) -> np.ndarray:
    """Dense ``Phi (B, n, n)`` from ``transition_reduced_batch``'s block."""
    B = T.shape[0]
    Phi = np.broadcast_to(np.eye(n), (B, n, n)).copy()
    c = np.r_[0:COMMON, n - K_SIZE : n]
    Phi[:, 0:COMMON, c] = T
    return Phi
