"""Compiled (Numba) twins of ``core.errorstate``: the attitude error state (the multiplicative EKF's chart).

The numpy functions are the reference (their docstrings give the equations); here, one
trial at a time, float64, ``nogil``, ``cache=True`` (the batch entry points of both charts,
``chart = 2`` here, are in ``core.kernels.charts``). The error state is
``eps = [d rho, d rho_dot, d omega, a, d P_1 .. d P_N, d k]`` (``n - 1``), additive on every
block but the attitude, where ``q = dq(a) (x) q_ref`` with ``dq(a) = [1, a/2] / |[1, a/2]|``:

- ``_chart``, ``_local`` (its inverse), ``_chart_jacobian`` (``S = dx/deps`` at any ``eps``:
  the identity with the column shift past the quaternion, and ``R(q_ref) d dq/d a`` on the
  quaternion rows), ``_error_map`` (``T = deps/dx`` at ``x_ref``: the same shift, and
  ``Xi = 2 [R(q_ref^*)]_vec`` on the attitude rows);
- ``_measure_attitude``: ``h(x_ref [+] eps)`` and the row-sparse ``H_eps = H S``. ``S`` only mixes the
  4 quaternion columns of ``H`` into the 3 attitude columns, so a feature's row keeps its 16
  non-zeros but one (``rho, rho_dot, omega``, ``a``, its point: 15) and a pseudo row its 9 but
  one (``omega``, ``a``, ``k``: 8), in the ``NNZ = 16`` layout of ``model.measure_batch`` that
  ``core.kernels.update`` runs the EKF and the IEKF on (``measurement_columns``).

The error-state covariance predict of this chart is ``aligned.predict_covariance_batch``
with ``chart = 2`` (the same ``Phi_e = T(x-) Phi S(x+)`` with this module's ``S`` and ``T``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..layout import E_OMEGA, E_POINTS, E_ROT, E_SHIFT, K_SIZE, POINTS, QUAT, VEC
from .model import H_POINT, NNZ, PS_K, PS_QUAT, Q_END, _measure_one, n_measurements, row_columns
from .rows import _copy_row

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")

ATT = E_ROT  # first entry of the attitude error ``a`` (the quaternion's in the state: QUAT, the same offset)
A_END = ATT + VEC
HE_POINT = E_POINTS  # a feature row's point columns in the row-sparse H_eps
PSE_K = PS_QUAT + VEC  # a pseudo row's k columns in the row-sparse H_eps (omega, a, k)


@njit(**_JIT)
def _qmul(p, q, out):
    """``out = p (x) q``, the Hamilton product (``quaternion.multiply``); ``out`` is neither input."""
    out[0] = p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3]
    out[1] = p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2]
    out[2] = p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1]
    out[3] = p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0]


@njit(**_JIT)
def _small_quaternion(d, dq):
    """``dq(d) = [1, d/2] / |[1, d/2]|`` (``errorstate.small_quaternion``)."""
    u1, u2, u3 = 0.5 * d[0], 0.5 * d[1], 0.5 * d[2]
    s = math.sqrt(1.0 + u1 * u1 + u2 * u2 + u3 * u3)
    dq[0], dq[1], dq[2], dq[3] = 1.0 / s, u1 / s, u2 / s, u3 / s


@njit(**_JIT)
def _small_quaternion_jacobian(d, Sq):
    """``d dq / d d`` (4 x 3): ``(I - p p^T) [0; I/2] / |u|`` (``errorstate.small_quaternion_jacobian``)."""
    u = np.empty(4)
    u[0], u[1], u[2], u[3] = 1.0, 0.5 * d[0], 0.5 * d[1], 0.5 * d[2]
    s = math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2] + u[3] * u[3])
    for a in range(4):
        for j in range(3):
            Sq[a, j] = ((0.5 if a == j + 1 else 0.0) - (u[a] / s) * (u[j + 1] / s) * 0.5) / s


@njit(**_JIT)
def _chart(xr, e, out):
    """``out = x_ref [+] eps`` (``errorstate.chart``): additive, ``q = dq(a) (x) q_ref``."""
    n = xr.shape[0]
    for i in range(QUAT):
        out[i] = xr[i] + e[i]
    for i in range(POINTS, n):
        out[i] = xr[i] + e[i - E_SHIFT]
    dq = np.empty(4)
    _small_quaternion(e[ATT:A_END], dq)
    _qmul(dq, xr[QUAT:Q_END], out[QUAT:Q_END])  # dq(a) (x) q_ref


@njit(**_JIT)
def _local(xr, x, e):
    """``eps`` with ``x = x_ref [+] eps`` (``errorstate.local``): ``a = 2 vec(dq) / dq_0``,
    ``dq = q (x) normalize(q_ref)^* / |q|``; the difference elsewhere."""
    n = x.shape[0]
    for i in range(QUAT):
        e[i] = x[i] - xr[i]
    for i in range(POINTS, n):
        e[i - E_SHIFT] = x[i] - xr[i]
    s0, s1, s2, s3 = xr[QUAT], xr[QUAT + 1], xr[QUAT + 2], xr[QUAT + 3]
    p0, p1, p2, p3 = x[QUAT], x[QUAT + 1], x[QUAT + 2], x[QUAT + 3]
    nr = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2 + s3 * s3)
    nx = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2 + p3 * p3)
    r0, r1, r2, r3 = s0 / nr, -(s1 / nr), -(s2 / nr), -(s3 / nr)
    d0 = (p0 * r0 - p1 * r1 - p2 * r2 - p3 * r3) / nx
    e[ATT] = 2.0 * ((p0 * r1 + p1 * r0 + p2 * r3 - p3 * r2) / nx) / d0
    e[ATT + 1] = 2.0 * ((p0 * r2 - p1 * r3 + p2 * r0 + p3 * r1) / nx) / d0
    e[ATT + 2] = 2.0 * ((p0 * r3 + p1 * r2 - p2 * r1 + p3 * r0) / nx) / d0


@njit(**_JIT)
def _quat_times(q, M, out, s):
    """``out = L(q) M`` (``s = 1``: ``L(q) r = q (x) r``, ``aligned.left_matrix``) or ``R(q) M`` (``s = -1``:
    ``R(q) p = p (x) q``, ``errorstate.right_matrix``), ``M 4 x 3``: the two differ in the sign of the
    cross-product terms only (``s`` times them is exact, so either is the product written out)."""
    q0, q1, q2, q3 = q[0], q[1], q[2], q[3]
    c1, c2, c3 = s * q1, s * q2, s * q3
    for j in range(3):
        m0, m1, m2, m3 = M[0, j], M[1, j], M[2, j], M[3, j]
        out[0, j] = q0 * m0 - q1 * m1 - q2 * m2 - q3 * m3
        out[1, j] = q1 * m0 + q0 * m1 - c3 * m2 + c2 * m3
        out[2, j] = q2 * m0 + c3 * m1 + q0 * m2 - c1 * m3
        out[3, j] = q3 * m0 - c2 * m1 + c1 * m2 + q0 * m3


@njit(**_JIT)
def _chart_jacobian(xr, e, S):
    """``S = d (x_ref [+] eps) / d eps`` (``n x n-1``, ``errorstate.chart_jacobian``), written in full."""
    n = xr.shape[0]
    S[:, :] = 0.0
    for i in range(QUAT):
        S[i, i] = 1.0
    for i in range(POINTS, n):
        S[i, i - E_SHIFT] = 1.0
    Sq = np.empty((4, 3))
    _small_quaternion_jacobian(e[ATT:A_END], Sq)
    _quat_times(xr[QUAT:Q_END], Sq, S[QUAT:Q_END, ATT:A_END], -1.0)


@njit(**_JIT)
def _error_map(xr, T):
    """``T = d eps / d x`` at ``x_ref`` (``n-1 x n``, ``errorstate.error_map``), written in full."""
    n = xr.shape[0]
    T[:, :] = 0.0
    for i in range(QUAT):
        T[i, i] = 1.0
    for i in range(POINTS, n):
        T[i - E_SHIFT, i] = 1.0
    q = xr[QUAT:Q_END]
    qn = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    q0, q1, q2, q3 = q[0] / qn, q[1] / qn, q[2] / qn, q[3] / qn
    # Xi = 2 [R(q^*)]_{1:4, :}, q^* = [q0, -q1, -q2, -q3]
    a, c = ATT, QUAT
    T[a, c], T[a, c + 1], T[a, c + 2], T[a, c + 3] = -2.0 * q1, 2.0 * q0, -2.0 * q3, 2.0 * q2
    T[a + 1, c], T[a + 1, c + 1], T[a + 1, c + 2], T[a + 1, c + 3] = -2.0 * q2, 2.0 * q3, 2.0 * q0, -2.0 * q1
    T[a + 2, c], T[a + 2, c + 1], T[a + 2, c + 2], T[a + 2, c + 3] = -2.0 * q3, -2.0 * q2, 2.0 * q1, 2.0 * q0


@njit(**_JIT)
def _apply_error_map(T, src, dst, lower=False):
    """``dst = T src`` for ``T = errorstate.error_map`` (``_error_map``, ``n-1 x n``) from its non-zeros, ``src (n, m)``.

    ``T`` is the identity on ``rho, rho_dot, omega`` (rows and columns 0-8), ``Xi = 2 [R(q^*)]_{1:4, :}`` from the
    quaternion's columns (9-12) onto the attitude's rows (9-11), and the identity shifted by one column on the points
    and ``k`` (row ``r``, column ``r + 1``): each row of ``dst`` is a row of ``src`` or a sum of four, ``O(n m)``
    instead of the dense product's ``O(n^2 m)``. The rows of ``src`` are copied exactly (the dense product adds exact
    zeros to them); an attitude row is ``(t0 s0 + t1 s1) + (t2 s2 + t3 s3)``.

    ``lower``: only the lower triangle of ``dst`` (square), the columns ``c <= r``: for a symmetric product whose
    upper triangle is mirrored after (each entry the same sum as in the full product).
    """
    ne, mm = dst.shape
    for r in range(ne):
        m = min(r + 1, mm) if lower else mm
        if r < ATT:
            _copy_row(dst, r, src, r, m)
        elif r < A_END:
            t0, t1, t2, t3 = T[r, QUAT], T[r, QUAT + 1], T[r, QUAT + 2], T[r, QUAT + 3]
            for c in range(m):
                dst[r, c] = (t0 * src[QUAT, c] + t1 * src[QUAT + 1, c]) + (t2 * src[QUAT + 2, c]
                                                                        + t3 * src[QUAT + 3, c])  # fmt: skip
        else:
            _copy_row(dst, r, src, r + E_SHIFT, m)


# --- measurement ----------------------------------------------------------------


@njit(**_JIT)
def _measure_attitude(xr, e, model, alpha, compute_jac, hx, Hval, xt, D, dD):
    """``h(x_ref [+] eps)`` and the row-sparse ``H_eps`` of one trial (module docstring); ``xt``: the charted state.

    From ``model._measure_one``'s full-state rows at ``xt``: the quaternion columns ``H_q`` become
    the attitude columns ``H_q R(q_ref) d dq/d a``; the point's columns (and ``k``'s) move one to
    the left.
    """
    _chart(xr, e, xt)
    _measure_one(xt, model, alpha, compute_jac, hx, Hval, D, dD)
    if not compute_jac:
        return
    Sq = np.empty((4, 3))
    RSq = np.empty((4, 3))
    _small_quaternion_jacobian(e[ATT:A_END], Sq)
    _quat_times(xr[QUAT:Q_END], Sq, RSq, -1.0)
    nf = n_measurements(model.vis.shape[0], model.disparity, False)  # the features' rows
    h = np.empty(NNZ)
    for r in range(nf):  # [rho, rho_dot, omega (9), q (4), P_i (3)] -> [.. (9), a (3), P_i (3), pad]
        for k in range(NNZ):
            h[k] = Hval[r, k]
        for j in range(3):
            Hval[r, ATT + j] = (h[QUAT] * RSq[0, j] + h[QUAT + 1] * RSq[1, j] + h[QUAT + 2] * RSq[2, j]
                                + h[QUAT + 3] * RSq[3, j])  # fmt: skip
            Hval[r, HE_POINT + j] = h[H_POINT + j]
        for k in range(HE_POINT + VEC, NNZ):
            Hval[r, k] = 0.0
    if model.pseudo:
        _pseudo_rows_rotated(Hval, nf, RSq, h)


@njit(**_JIT)
def _pseudo_rows_rotated(Hval, nf, M, h):
    """The 3 pseudo rows (from row ``nf``) in an error-state chart: ``[omega (3), q (4), k (2)]`` of
    ``model._pseudo_rows`` become ``[omega, H_q M (3), k]``, ``M = dq / d(rotation)`` (4 x 3) of the chart; ``h``:
    scratch of ``NNZ``."""
    for r in range(nf, nf + 3):
        for k in range(NNZ):
            h[k] = Hval[r, k]
        for j in range(3):
            Hval[r, PS_QUAT + j] = (h[PS_QUAT] * M[0, j] + h[PS_QUAT + 1] * M[1, j] + h[PS_QUAT + 2] * M[2, j]
                                    + h[PS_QUAT + 3] * M[3, j])  # fmt: skip
        Hval[r, PSE_K], Hval[r, PSE_K + 1] = h[PS_K], h[PS_K + 1]
        for k in range(PSE_K + K_SIZE, NNZ):
            Hval[r, k] = 0.0


def measurement_columns(ne, vis, channels, pseudo):
    """Column indices ``(m, 16)`` of the row-sparse ``H_eps``: a feature's rows see ``rho, rho_dot, omega, a``
    and its point, the pseudo rows ``omega, a, k``."""
    k = np.arange(ne - K_SIZE, ne)
    return row_columns(vis, channels, np.arange(E_POINTS), E_POINTS, np.arange(0),
                       np.concatenate((np.arange(E_OMEGA, A_END), k)), pseudo)  # fmt: skip
