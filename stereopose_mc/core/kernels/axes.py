"""Compiled (Numba) per-axis errors and standard deviations: the twin of ``mc.trial.axis_errors``.

Per trial, the attitude-chart error ``eps`` with ``x_hat = x_true [+] eps``
(``errorstate.estimation_error``) on the rows rho, rho_dot, omega, the attitude error vector
``a`` and k (``rundir.tables.AXES``), and the filter's standard deviation of each, the square
root of the diagonal of ``M P M^T`` restricted to those rows, ``M`` mapping the covariance's
coordinates to ``eps`` at ``x_hat``:

- ``FULL`` (``P`` of the full state, ``n x n``): ``M = errorstate.error_map(x_hat)``, identity
  rows but for the attitude, ``Xi = 2 [R(q_hat^*)]_vec`` on the quaternion (``q_hat`` normalized):
  ``var(a) = diag(Xi P_qq Xi^T)``;
- ``ALIGNED`` (the aligned chart's ``P``): ``M = T_attitude S_aligned`` by its rows of non-zeros
  (``consistency._attitude_rows``) and its blocks ``M P M^T`` as the block NEES form them
  (``consistency._block_points``, ``_block``);
- ``ATTITUDE`` (the attitude chart's own ``P``): ``M = I``, ``P``'s diagonal.

A negative variance gives NaN (as numpy's ``sqrt(where(var >= 0, var, nan))``); a state or
covariance that is not finite gives NaN through the arithmetic. In ``AXIS_UNITS``: omega and the
attitude in degrees (``mc.trial._AXIS_SCALE``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import writable as _writable
from ._refs import borrow
from .aligned import _local
from .consistency import N_AXES, _attitude_rows, _axis_row, _block, _block_points, _estimation_error, _point_rows_sum
from ..layout import E_OMEGA, E_POINTS, E_RHO, E_RHO_DOT, E_ROT, K_SIZE, QUAT, VEC
from .model import n_points as _n_points

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")

FULL, ALIGNED, ATTITUDE = 0, 1, 2
CHARTS = {"full": FULL, "aligned": ALIGNED, "attitude": ATTITUDE}


@njit(**_JIT)
def _full_variances(xh, P, var):
    """``var[:12]`` of a full-state ``P``: its diagonal on rho, rho_dot, omega, ``diag(Xi P_qq Xi^T)`` on ``a``."""
    for r in range(E_ROT):
        var[r] = P[r, r]
    q0, q1, q2, q3 = xh[QUAT], xh[QUAT + 1], xh[QUAT + 2], xh[QUAT + 3]
    s = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    q0, q1, q2, q3 = q0 / s, q1 / s, q2 / s, q3 / s
    for a in range(3):  # Xi's rows: 2 [R(q^*)]_vec
        if a == 0:
            x0, x1, x2, x3 = -q1, q0, -q3, q2
        elif a == 1:
            x0, x1, x2, x3 = -q2, q3, q0, -q1
        else:
            x0, x1, x2, x3 = -q3, -q2, q1, q0
        row = (2.0 * x0, 2.0 * x1, 2.0 * x2, 2.0 * x3)
        v = 0.0
        for i in range(4):
            t = 0.0
            for j in range(4):
                t += P[QUAT + i, QUAT + j] * row[j]
            v += row[i] * t
        var[E_ROT + a] = v


@njit(**_JIT)
def axis_errors_batch(x_hat, P, x_true, chart, scale):
    """``(err, sigma)`` ``(B, 14)`` each, in ``AXIS_UNITS`` (``scale (14,)``); ``x_true (B, n)``; ``chart``: ``FULL``,
    ``ALIGNED`` or ``ATTITUDE`` (the chart of ``P``)."""
    B, n = x_hat.shape
    ne = n - 1
    N = _n_points(n)
    p1 = E_POINTS + VEC * N
    k = VEC + VEC * N  # the most non-zeros of a row of M (rho_dot: 1 + 2 + 3N)
    err = np.empty((B, N_AXES))
    sig = np.empty((B, N_AXES))
    eps, e, var = np.empty(ne), np.empty(ne), np.empty(N_AXES)
    D, Dt, R = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    dq, tmp, v3, Wp = np.empty(4), np.empty(4), np.empty((6, 3)), np.empty((6, 3))
    cnt, cols, vals = np.zeros(ne, np.int64), np.zeros((ne, k), np.int64), np.zeros((ne, k))
    Y, C, Sp = np.empty((3, ne)), np.empty((3, 3)), np.empty((3, ne))
    x_hat, P, x_true = borrow((x_hat, P, x_true))  # (_refs: the caller's arrays, held by it)
    for t in range(B):
        xh, xt, Pt = x_hat[t], x_true[t], P[t]
        nh, nt = _local(xh, xt, e, D, Dt, R, dq, tmp, v3)  # (D, v_hat = v3[2] for M; e not used)
        _estimation_error(xh, xt, nh, nt, eps, tmp, dq)
        if chart == FULL:
            _full_variances(xh, Pt, var)
            for j in range(K_SIZE):
                var[E_POINTS + j] = Pt[n - K_SIZE + j, n - K_SIZE + j]
        elif chart == ATTITUDE:
            for r in range(E_POINTS):
                var[r] = Pt[r, r]
            for j in range(K_SIZE):
                var[E_POINTS + j] = Pt[ne - K_SIZE + j, ne - K_SIZE + j]
        else:
            _attitude_rows(xh, N, D, v3[2], cnt, cols, vals, Wp)
            _point_rows_sum(Pt, N, Sp)
            for b in range(5):  # rho, rho_dot, omega, attitude, k: (lo, hi) rows, (c0, c1) their columns
                lo = (E_RHO, E_RHO_DOT, E_OMEGA, E_ROT, p1)[b]
                hi = (E_RHO_DOT, E_OMEGA, E_ROT, E_POINTS, ne)[b]
                c0 = (E_RHO, E_RHO_DOT, E_OMEGA, E_ROT, p1)[b]
                c1 = (p1, p1, E_ROT, E_POINTS, ne)[b]
                if b < 2:
                    _block_points(cnt, cols, vals, lo, hi, Pt, Y, C, Sp, Wp[3 * b : 3 * b + 3], N, c0, c1)
                else:
                    _block(cnt, cols, vals, lo, hi, Pt, Y, C, c0, c1)
                at = lo if b < 4 else E_POINTS
                for a in range(hi - lo):
                    var[at + a] = C[a, a]
        for r in range(N_AXES):
            err[t, r] = eps[_axis_row(r, ne)] * scale[r]
            v = var[r]
            sig[t, r] = math.sqrt(v) * scale[r] if v >= 0.0 else np.nan
    return err, sig


def axis_errors(x_hat: np.ndarray, P: np.ndarray, x_true: np.ndarray, chart: str, scale: np.ndarray):
    """``mc.trial.axis_errors`` of ``x_hat (B, n)``, ``P`` (``(B, n, n)`` full state or ``(B, n-1, n-1)`` in
    ``chart``) against ``x_true (n,)`` or ``(B, n)``, on the compiled kernel (``scale``: ``mc.trial._AXIS_SCALE``)."""
    x_hat = _writable(x_hat)
    code = FULL if P.shape[-1] == x_hat.shape[-1] else CHARTS[chart]
    return axis_errors_batch(x_hat, _writable(P), _writable(np.broadcast_to(x_true, x_hat.shape)), code,
                             _writable(scale))  # fmt: skip
