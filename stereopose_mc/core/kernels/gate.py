"""Compiled innovation-covariance blocks and distances of the per-feature gate, from the row-sparse ``H``.

The twin of ``filters.gating.linearized_blocks`` (which takes the dense ``H``): for each trial and each of the
first ``F`` features, the ``C x C`` block

    S_f = H_f P H_f^T + R_f

where ``H_f`` is the feature's ``C`` rows. In the row-sparse ``H`` of ``core.kernels.model`` (and of the charts,
``core.kernels.aligned``, ``core.kernels.attitude``) the ``C`` rows of a feature hold the same 16 columns ``c``
(``rho, rho_dot, omega, q`` or their errors, and its own point), so

    S_f = V_f P[c, c] V_f^T + R_f                      (V_f: the rows' 16 values, C x 16)

costs ``C 16^2 + C^2 16`` products per feature (the dense path: ``C n^2`` per feature, with ``n`` up to 87 and
a dense ``H`` of ``B m n`` values made first). In the aligned chart three of the columns are virtual (the sums
of the points' columns: ``aligned.virtual_rows``); ``P`` is then read through them,

    P[n + a, j] = sum_p P[E_POINTS + 3 p + a, j],   P[n + a, n + b] = sum_p P[n + a, E_POINTS + 3 p + b],

a copy of ``P`` with these rows and columns formed once per trial. Padding entries (value 0) add nothing.

The gate's distance of each block, ``d_f^2 = nu_f^T S_f^-1 nu_f`` (``filters.gating.distances2``, by LU there), comes
from the block's own Cholesky factor while it is in cache.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..layout import E_POINTS, VEC, e_n_points
from .aligned import virtual_rows

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")
_e_n_points = njit(inline="always", error_model="numpy")(e_n_points)


@njit(**_JIT)
def _augmented(P, Pa):
    """``Pa (n + 3, n + 3)``: ``P`` with the aligned chart's virtual rows and columns (the point sums),
    ``Pa[n + a, j] = sum_p P[E_POINTS + 3 p + a, j]`` (``aligned.virtual_rows``), mirrored onto the columns, and
    ``Pa[n + a, n + c] = sum_p Pa[n + a, E_POINTS + 3 p + c]``."""
    n = P.shape[0]
    N = _e_n_points(n)
    for i in range(n):
        for j in range(n):
            Pa[i, j] = P[i, j]
    virtual_rows(P, Pa)
    for a in range(VEC):
        for j in range(n):
            Pa[j, n + a] = Pa[n + a, j]
        for c in range(VEC):
            s = 0.0
            for p in range(N):
                s += Pa[n + a, E_POINTS + VEC * p + c]
            Pa[n + a, n + c] = s


@njit(inline="always", **_JIT)
def _distance2(S, b, f, nu, r0, Lc, w):
    """``nu_f^T S_f^-1 nu_f`` of block ``S[b, f]`` and the rows ``r0 ..`` of ``nu[b]``, by the Cholesky factor ``Lc``
    of ``S_f`` (``S_f = Lc Lc^T``, ``w = Lc^-1 nu_f``, ``d^2 = |w|^2``); NaN where ``S_f`` is not positive definite."""
    C = Lc.shape[0]
    for i in range(C):
        for j in range(i + 1):
            s = S[b, f, i, j]
            for q in range(j):
                s -= Lc[i, q] * Lc[j, q]
            if i == j:
                if not s > 0.0:  # (also a NaN)
                    return np.nan
                Lc[i, i] = math.sqrt(s)
            else:
                Lc[i, j] = s / Lc[j, j]
    d2 = 0.0
    for i in range(C):
        s = nu[b, r0 + i]
        for q in range(i):
            s -= Lc[i, q] * w[q]
        w[i] = s / Lc[i, i]
        d2 += w[i] * w[i]
    return d2


@njit(**_JIT)
def innovation_blocks_batch(Hval, cols, P, R, nu, n_features, channels, virtual, offered):
    """``(S (B, F, C, C), d2 (B, F))``: ``S_f = H_f P H_f^T + R_f`` of the first ``F C`` rows (module docstring) and
    the gate's squared Mahalanobis distances ``d_f^2 = nu_f^T S_f^-1 nu_f`` (NaN where ``S_f`` is not positive
    definite: ``filters.compiled.gate_distances`` gives those to ``gating.distances2``, as before this kernel).

    ``Hval (B, m, k)`` the values of the row-sparse ``H`` at columns ``cols (m, k)`` (each feature's ``C`` rows with
    the same columns: ``filters.compiled._constants`` checks it), ``P (B, n, n)``, ``R (B, m)`` the diagonal
    measurement variances, ``nu (B, m)`` the innovations; ``virtual``: columns ``n .. n + 2`` are the aligned
    chart's point sums (``P`` read through its copy with them, ``_augmented``). Per feature, ``P[c, c]`` gathered
    once for its ``C`` rows, then ``T = V_f P[c, c]`` over each row's non-zero values and ``S_f = T V_f^T + R_f``,
    each block exactly symmetric (its lower triangle summed, then mirrored). ``offered (B, F)``: the features to
    evaluate, the others' ``S_f`` and ``d_f^2`` NaN, not computed (features out of a trial's own view, masked rows
    of a batch updated as one: ``filters.compiled.masks_visibility``); ``(0, F)``: all.
    """
    B, n = P.shape[0], P.shape[1]
    F, C, k = n_features, channels, cols.shape[1]
    S = np.empty((B, F, C, C))
    d2 = np.empty((B, F))
    Pa = np.empty((n + VEC, n + VEC) if virtual else (0, 0))
    Pf = np.empty((k, k))
    T = np.empty((C, k))
    Lc = np.empty((C, C))
    w = np.empty(C)
    some = offered.shape[0] == B
    for b in range(B):
        if virtual:
            _augmented(P[b], Pa)
        Q = Pa if virtual else P[b]
        for f in range(F):
            if some and not offered[b, f]:
                for c in range(C):
                    for d in range(C):
                        S[b, f, c, d] = np.nan
                d2[b, f] = np.nan
                continue
            r0 = f * C
            for i in range(k):  # P[c, c] of the feature's columns
                ci = cols[r0, i]
                for j in range(k):
                    Pf[i, j] = Q[ci, cols[r0, j]]
            for c in range(C):  # T = V_f P[c, c]: each non-zero value times a row of P[c, c]
                for j in range(k):
                    T[c, j] = 0.0
                for i in range(k):
                    h = Hval[b, r0 + c, i]
                    if h != 0.0:
                        for j in range(k):
                            T[c, j] += h * Pf[i, j]
            for c in range(C):  # S_f = T V_f^T + R_f
                for d in range(c + 1):
                    s = 0.0
                    for j in range(k):
                        s += T[c, j] * Hval[b, r0 + d, j]
                    S[b, f, c, d] = s
                    S[b, f, d, c] = s
                S[b, f, c, c] += R[b, r0 + c]
            d2[b, f] = _distance2(S, b, f, nu, r0, Lc, w)
    return S, d2
