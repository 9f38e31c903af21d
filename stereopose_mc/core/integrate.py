"""Batched adaptive Dormand-Prince 8(5,3) integration, one step size per trial.

``dop853_batch`` integrates ``B`` independent systems ``y' = f(y)`` (``y (B, m)``) with
the coefficients and the error estimate of scipy's ``DOP853`` (Hairer's DOP853:
``err = |h| |e5|^2 / sqrt(m (|e5|^2 + 0.01 |e3|^2))`` in the weighted RMS norm with
``scale = atol + rtol max(|y|, |y_new|)``; step factor ``0.9 err^(-1/8)`` within
``[0.2, 10]``). Each trial has its own step size, accepts or rejects its own steps and
lands exactly on every output time, so its trajectory is the same bits whatever other
trials share the batch (all arithmetic is elementwise or a reduction along one row).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.integrate._ivp import dop853_coefficients as dop

Array = NDArray[np.float64]
_S = dop.N_STAGES
_A, _B, _C, _E3, _E5 = dop.A[:_S, :_S], dop.B, dop.C[:_S], dop.E3, dop.E5
SAFETY, MIN_FACTOR, MAX_FACTOR = 0.9, 0.2, 10.0


def _rms(v: Array) -> Array:
    """Row-wise RMS ``(B,)`` of ``v (B, m)``."""
    v = np.ascontiguousarray(v)
    return np.sqrt(np.einsum("ij,ij->i", v, v) / v.shape[-1])


def _initial_step(f0: Array, y0: Array, fun, rtol: float, atol: Array, span: float) -> Array:
    """Hairer's starting step (scipy's ``select_initial_step``), per row."""
    scale = atol + np.abs(y0) * rtol
    d0, d1 = _rms(y0 / scale), _rms(f0 / scale)
    h0 = np.where((d0 < 1e-5) | (d1 < 1e-5), 1e-6, 0.01 * d0 / np.where(d1 > 0, d1, 1.0))
    h0 = np.minimum(h0, span)
    f1 = fun(y0 + h0[:, None] * f0)
    d2 = _rms((f1 - f0) / scale) / h0
    h1 = np.where((d1 <= 1e-15) & (d2 <= 1e-15), np.maximum(1e-6, h0 * 1e-3),
                  (0.01 / np.maximum(d1, d2)) ** (1.0 / 8.0))  # fmt: skip
    return np.minimum(np.minimum(100 * h0, h1), span)


def _step(fun, y: Array, f: Array, h: Array) -> tuple[Array, Array, Array]:
    """One DOP853 step of every row: ``y_new``, ``f(y_new)`` and the stages ``K (S+1, b, m)``."""
    K = np.empty((_S + 1,) + y.shape)
    K[0] = f
    hc = h[:, None]
    for s in range(1, _S):
        dy = np.zeros_like(y)
        for j in range(s):
            if _A[s, j] != 0.0:
                dy += _A[s, j] * K[j]
        K[s] = fun(y + hc * dy)
    acc = np.zeros_like(y)
    for j in range(_S):
        if _B[j] != 0.0:
            acc += _B[j] * K[j]
    y_new = y + hc * acc
    K[_S] = fun(y_new)
    return y_new, K[_S], K


def _error(K: Array, h: Array, scale: Array) -> Array:
    e5 = np.zeros(K.shape[1:])
    e3 = np.zeros(K.shape[1:])
    for j in range(_S + 1):
        if _E5[j] != 0.0:
            e5 += _E5[j] * K[j]
        if _E3[j] != 0.0:
            e3 += _E3[j] * K[j]
    e5 /= scale
    e3 /= scale
    m = K.shape[-1]
    n5 = np.einsum("ij,ij->i", e5, e5)
    n3 = np.einsum("ij,ij->i", e3, e3)
    denom = n5 + 0.01 * n3
    with np.errstate(invalid="ignore", divide="ignore"):
        err = np.abs(h) * n5 / np.sqrt(denom * m)
    return np.where(denom > 0, err, 0.0)


def dop853_batch(fun: Callable[[Array], Array], y0: Array, t: Array, rtol: float, atol: Array,
                 max_steps: int = 1_000_000) -> Array:  # fmt: skip
    """``y (B, len(t), m)`` at the times ``t`` (increasing, ``t[0]`` the initial time).

    ``fun(y (b, m)) -> (b, m)`` is autonomous and row-wise; ``atol`` is ``(m,)`` or ``(B, m)``.
    """
    y0 = np.asarray(y0, dtype=float)
    B, m = y0.shape
    atol = np.broadcast_to(np.asarray(atol, dtype=float), (B, m))
    out = np.empty((B, t.size, m))
    out[:, 0] = y0
    y = y0.copy()
    f = fun(y)
    h = _initial_step(f, y, fun, rtol, atol, float(t[-1] - t[0]))
    rejected = np.zeros(B, bool)
    steps = 0
    for k in range(1, t.size):
        T = float(t[k])
        tt = np.full(B, float(t[k - 1]))
        active = np.arange(B)
        while active.size:
            steps += 1
            if steps > max_steps:
                raise RuntimeError("truth integration: too many steps")
            ya, fa, ta = y[active], f[active], tt[active]
            left = T - ta
            last = h[active] >= left * (1.0 - 1e-12)
            ha = np.where(last, left, h[active])
            y_new, f_new, K = _step(fun, ya, fa, ha)
            scale = atol[active] + np.maximum(np.abs(ya), np.abs(y_new)) * rtol
            err = _error(K, ha, scale)
            ok = err < 1.0
            with np.errstate(divide="ignore"):
                grow = np.where(err == 0.0, MAX_FACTOR, np.minimum(MAX_FACTOR, SAFETY * err ** (-1.0 / 8.0)))
                shrink = np.maximum(MIN_FACTOR, SAFETY * err ** (-1.0 / 8.0))
            grow = np.where(rejected[active], np.minimum(1.0, grow), grow)
            # a step shortened to land on T leaves the step size as it was
            h[active] = np.where(ok, np.where(last, h[active], ha * grow), ha * shrink)
            rejected[active] = ~ok
            acc = active[ok]
            y[acc], f[acc] = y_new[ok], f_new[ok]
            tt[acc] = np.where(last[ok], T, ta[ok] + ha[ok])
            active = active[~(ok & last)]
        out[:, k] = y
    return out
