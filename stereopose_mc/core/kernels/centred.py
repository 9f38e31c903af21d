"""The centred point coordinates of the aligned chart, for the compiled update's large ``n`` (``LARGE_N``).

The aligned chart's features see the points only through their deviations from the centroid, so the centroid's
error (the gauge) is never measured and keeps its prior variance while the deviations shrink. Whitened by the
Cholesky factor of ``P`` itself, a feature's row is the difference of two large rows (its point's and the mean's),
and the information form of the large-``n`` whitening (``whiten._whiten_information``) squares that
cancellation. Past ``LARGE_N`` columns the aligned chart is therefore whitened in centred coordinates
``e' = T e``: the common block, then ``e_bar`` (the points' mean error, 3), then ``d_f = e_Pf - e_bar`` for the
first ``N - 1`` points, then ``k``: ``P' = T P T^T = L' L'^T`` and ``L = T^-1 L'`` (a square root of ``P``, not
triangular). A feature's row then sees its own ``d_f`` (the last point: minus the sum of all ``d``, a virtual
column of small rows) and ``e_bar`` with the coefficient ``h_own + N h_virtual`` (~0): an arrow again.
"""

from __future__ import annotations

from numba import njit

from ..layout import E_POINTS, VEC
from .model import NNZ
from .rows import _mirror_lower, _pair_products

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")


@njit(**_JIT)
def _center_cov(P, Pc, tmp, N):
    """``Pc = T P T^T = T (T P)^T`` (``P`` symmetric; the centered coordinates above; ``tmp`` an ``n x n``
    scratch): two passes of ``_center_rows`` with a transposed copy between them. Symmetric to round-off: its lower
    triangle is what the Cholesky factorization reads."""
    _center_rows(P, Pc, N)
    tmp[:, :] = Pc.T
    _center_rows(tmp, Pc, N)


@njit(**_JIT)
def _uncenter_cov(Pc, P, tmp, N):
    """``P = T^-1 Pc T^-T``: ``T^-1`` on the rows, then on each row as a vector (no sums to compensate: the
    deviations are added to the mean); exactly symmetric."""
    _uncenter_rows(Pc, tmp, N)
    for i in range(Pc.shape[0]):
        _uncenter_vec_to(tmp[i], P[i], N)
    _mirror_lower(P)


@njit(**_JIT)
def _copy_other_rows(M, out, N):
    """``out[i] = M[i]`` for the rows that ``T`` leaves alone: the common block (12) and ``k``."""
    for i in range(M.shape[0]):
        if i < E_POINTS or i >= E_POINTS + VEC * N:
            for j in range(M.shape[1]):
                out[i, j] = M[i, j]


@njit(**_JIT)
def _center_rows(M, out, N):
    """``out = T M`` by rows: the points' mean row, then each of the first ``N - 1`` point rows minus it.

    The mean is a compensated sum (Knuth's TwoSum on each term, branch-free): a point's deviation
    from the mean is small against the points' common (unmeasured) error, and a plain sum of ``N``
    rows would lose ~``N`` ulps of the large common part in it. ``out``'s first deviation rows hold
    the compensations until the mean is final; with one point there are none (``T`` is the identity: the mean of
    one point is that point), and the rows after it are ``k``'s or past the array: its row is copied."""
    k = M.shape[1]
    p0 = E_POINTS
    _copy_other_rows(M, out, N)
    if N == 1:
        for a in range(3):
            for j in range(k):
                out[p0 + a, j] = M[p0 + a, j]
        return
    for a in range(3):
        for j in range(k):
            out[p0 + a, j] = 0.0
            out[p0 + 3 + a, j] = 0.0
    for f in range(N):
        for a in range(3):
            for j in range(k):
                t = out[p0 + a, j]
                v = M[p0 + 3 * f + a, j]
                u = t + v
                bp = u - t
                out[p0 + 3 + a, j] += (t - (u - bp)) + (v - bp)
                out[p0 + a, j] = u
    for a in range(3):
        for j in range(k):
            out[p0 + a, j] = (out[p0 + a, j] + out[p0 + 3 + a, j]) / N
    for f in range(N - 1):
        for a in range(3):
            for j in range(k):
                out[p0 + 3 + 3 * f + a, j] = M[p0 + 3 * f + a, j] - out[p0 + a, j]


@njit(**_JIT)
def _uncenter_rows(M, out, N):
    """``out = T^-1 M`` by rows: ``e_Pf = d_f + e_bar`` (``f < N - 1``), ``e_P(N-1) = e_bar - sum_f d_f``."""
    k = M.shape[1]
    p0 = E_POINTS
    last = p0 + 3 * (N - 1)
    _copy_other_rows(M, out, N)
    for a in range(3):
        for j in range(k):
            out[last + a, j] = M[p0 + a, j]
    for f in range(N - 1):
        for a in range(3):
            for j in range(k):
                d = M[p0 + 3 + 3 * f + a, j]
                out[p0 + 3 * f + a, j] = d + M[p0 + a, j]
                out[last + a, j] -= d


@njit(**_JIT)
def _uncenter_vec_to(v, out, N):
    """``out = T^-1 v`` (``out`` may not be ``v``)."""
    n = v.shape[0]
    p0 = E_POINTS
    last = p0 + 3 * (N - 1)
    for i in range(p0):
        out[i] = v[i]
    for i in range(p0 + 3 * N, n):
        out[i] = v[i]
    s0, s1, s2 = v[p0], v[p0 + 1], v[p0 + 2]
    for f in range(N - 1):
        d0, d1, d2 = v[p0 + 3 + 3 * f], v[p0 + 4 + 3 * f], v[p0 + 5 + 3 * f]
        out[p0 + 3 * f] = d0 + v[p0]
        out[p0 + 3 * f + 1] = d1 + v[p0 + 1]
        out[p0 + 3 * f + 2] = d2 + v[p0 + 2]
        s0 -= d0
        s1 -= d1
        s2 -= d2
    out[last], out[last + 1], out[last + 2] = s0, s1, s2


@njit(**_JIT)
def _centered_virtual_rows(Laug, N):
    """``Laug[n + a] = sum_{f < N-1} L'[15 + 3 f + a]``: the rows of the last point's virtual column."""
    n = Laug.shape[1]
    for a in range(3):
        for j in range(n):
            Laug[n + a, j] = 0.0
    for f in range(N - 1):
        for a in range(3):
            for j in range(n):
                Laug[n + a, j] += Laug[E_POINTS + VEC + VEC * f + a, j]


@njit(**_JIT)
def _centered_model_rows(Hval, cols, Hc, cc, n, N):
    """The aligned chart's row-sparse ``H_e`` in the centered coordinates: ``H' = H_e T^-1`` (same layout).

    A point column ``12 + 3 f + a`` gives its value to ``d_f`` (column ``15 + 3 f + a``) and to ``e_bar``
    (``12 + a``), or for the last point to ``e_bar`` and, negated, to the virtual column ``n + a`` (the sum of
    every ``d``); a virtual column ``n + a`` of ``H_e`` (the sum of every point) gives ``N`` times its value to
    ``e_bar``. The other columns are unchanged."""
    m = Hval.shape[0]
    p0 = E_POINTS
    for r in range(m):
        eb0 = 0.0
        eb1 = 0.0
        eb2 = 0.0
        k = 0
        for q in range(NNZ):
            Hc[r, q] = 0.0
            cc[r, q] = 0
        for q in range(NNZ):
            h = Hval[r, q]
            c = cols[r, q]
            if h == 0.0:
                continue
            if c >= n:
                a = c - n
                h = h * N
            elif c >= p0 and c < p0 + 3 * N:
                f = (c - p0) // VEC
                a = (c - p0) - 3 * f
                if f < N - 1:
                    Hc[r, k] = h
                    cc[r, k] = p0 + 3 + 3 * f + a
                else:
                    Hc[r, k] = -h
                    cc[r, k] = n + a
                k += 1
            else:
                Hc[r, k] = h
                cc[r, k] = c
                k += 1
                continue
            if a == 0:
                eb0 += h
            elif a == 1:
                eb1 += h
            else:
                eb2 += h
        if eb0 != 0.0 or eb1 != 0.0 or eb2 != 0.0:
            Hc[r, k], cc[r, k] = eb0, p0
            Hc[r, k + 1], cc[r, k + 1] = eb1, p0 + 1
            Hc[r, k + 2], cc[r, k + 2] = eb2, p0 + 2


@njit(**_JIT)
def _sqrt_mul(L, z, out, cen, N, tmp):
    """``out = L z`` for the whitening's square root: ``L`` lower triangular, or (``cen``) ``T^-1 L' z`` (through
    ``tmp``)."""
    if cen:
        _lower_mul(L, z, tmp)
        _uncenter_vec_to(tmp, out, N)
    else:
        _lower_mul(L, z, out)


@njit(**_JIT)
def _lower_mul(L, z, out):
    """``out = L z`` (``L`` lower triangular), row ``i`` ``_dot_row(L, i, z, 0, i + 1)``, two rows per pass
    (``rows._pair_products``)."""
    _pair_products(L, z, out, True)
