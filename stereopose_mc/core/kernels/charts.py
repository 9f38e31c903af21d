"""Batch entry points of the two error-state charts: ``(B, .)`` in, one trial at a time, ``chart`` an argument.

``chart`` 1: the aligned error state (``core.kernels.aligned``, twin of ``core.aligned``);
2: the attitude error state (``core.kernels.attitude``, twin of ``core.errorstate``). The
same codes as the update kernels' (``core.kernels.update``; 0 there is the full state, which
has no chart). Float64, ``nogil``, ``cache=True``.

- ``chart_batch(chart, x_ref, e)``: ``x_ref [+] e`` ``(B, n)``; ``local_batch(chart, x_ref, x)``:
  its inverse ``(B, n-1)``;
- ``chart_jacobian_batch(chart, x_ref, e)``: ``S = dx/de`` ``(B, n, n-1)`` at any ``e``;
  ``error_map_batch(chart, x_ref)``: ``T = de/dx`` ``(B, n-1, n)``;
- ``measure_batch(chart, x_ref, e, ...)``: ``h(x_ref [+] e)`` ``(B, m)`` and the values
  ``(B, m, 16)`` of the row-sparse ``H_e = H S`` (columns: ``measurement_columns``; dense:
  ``dense``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..layout import CHART_ALIGNED
from . import aligned as ka
from . import attitude as kt
from .model import NNZ, n_measurements
from .model import dense as dense_rows

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")


@njit(**_JIT)
def chart_batch(chart, x_ref, e):
    """``x_ref [+] e`` of every trial, ``(B, n)`` (``aligned.chart`` or ``errorstate.chart``)."""
    B, n = x_ref.shape
    out = np.empty((B, n))
    Dref, R, v = np.empty((3, 3)), np.empty((3, 3)), np.empty(3)
    for b in range(B):
        if chart == CHART_ALIGNED:
            ka._chart(x_ref[b], e[b], out[b], Dref, R, v)
        else:
            kt._chart(x_ref[b], e[b], out[b])
    return out


@njit(**_JIT)
def local_batch(chart, x_ref, x):
    """``e = local(x_ref, x)`` of every trial, ``(B, n-1)`` (``aligned.local`` or ``errorstate.local``)."""
    B, n = x.shape
    out = np.empty((B, n - 1))
    D, Dt, R = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    dq, tmp, v3 = np.empty(4), np.empty(4), np.empty((6, 3))
    for b in range(B):
        if chart == CHART_ALIGNED:
            ka._local(x_ref[b], x[b], out[b], D, Dt, R, dq, tmp, v3)
        else:
            kt._local(x_ref[b], x[b], out[b])
    return out


@njit(**_JIT)
def chart_jacobian_batch(chart, x_ref, e):
    """``S (B, n, n-1)`` of every trial (``chart_jacobian``)."""
    B, n = x_ref.shape
    out = np.empty((B, n, n - 1))
    for b in range(B):
        if chart == CHART_ALIGNED:
            ka._chart_jacobian(x_ref[b], e[b], out[b])
        else:
            kt._chart_jacobian(x_ref[b], e[b], out[b])
    return out


@njit(**_JIT)
def error_map_batch(chart, x_ref):
    """``T (B, n-1, n)`` of every trial (``error_map``)."""
    B, n = x_ref.shape
    out = np.empty((B, n - 1, n))
    for b in range(B):
        if chart == CHART_ALIGNED:
            ka._error_map(x_ref[b], out[b])
        else:
            kt._error_map(x_ref[b], out[b])
    return out


@njit(**_JIT)
def measure_batch(chart, x_ref, e, model, alpha, compute_jac):
    """``h(x_ref [+] e) (B, m)`` and the values ``(B, m, 16)`` of the row-sparse ``H_e`` (``measurement_columns``);
    ``model``: a ``model.StepModel``, ``alpha (B, 3)``."""
    B, n = x_ref.shape
    m = n_measurements(model.vis.shape[0], model.disparity, model.pseudo)
    hx = np.empty((B, m))
    Hval = np.zeros((B, m, NNZ))
    xt = np.empty(n)
    D = np.empty((3, 3))
    dD = np.empty((4, 3, 3))
    for b in range(B):
        if chart == CHART_ALIGNED:
            ka._measure_aligned(x_ref[b], e[b], model, alpha[b], compute_jac, hx[b], Hval[b], xt, D, dD)
        else:
            kt._measure_attitude(x_ref[b], e[b], model, alpha[b], compute_jac, hx[b], Hval[b], xt, D, dD)
    return hx, Hval


def measurement_columns(chart: int, ne: int, vis: np.ndarray, channels: int, pseudo: bool) -> np.ndarray:
    """Column indices ``(m, 16)`` of the row-sparse ``H_e`` of ``measure_batch`` (the chart's own layout)."""
    return (ka if chart == CHART_ALIGNED else kt).measurement_columns(ne, vis, channels, pseudo)


def dense(chart: int, Hval: np.ndarray, cols: np.ndarray, ne: int) -> np.ndarray:
    """Dense ``H_e (B, m, ne)`` from the row-sparse one (the aligned chart's virtual columns added to every point)."""
    return ka.dense(Hval, cols, ne) if chart == CHART_ALIGNED else dense_rows(Hval, cols, ne)
