"""Whitening of the measurement rows for the compiled updates: ``Hw = R^-1/2 H L``, ``rw``, ``g`` and ``A``.

Twins of the whitened algebra in ``core.kalman.iekf_update``: with ``P = L L^T``, ``Hw = R^-1/2 H L``,
``rw = R^-1/2 (y - h)``, ``g = Hw^T rw`` and ``A = I + Hw^T Hw`` (the system both the EKF and the IEKF solve,
``core.kernels.update``). ``H`` is row-sparse (``model.NNZ`` values per row and their columns), so a row of
``Hw`` is a sum of a few rows of ``L``. ``_whiten`` forms them two rows at a time up to ``LARGE_N`` columns;
past it ``_whiten_information`` forms ``A = I + L^T (H^T R^-1 H) L`` from the arrow-shaped information instead
of the rows (its cost then follows the model's structure, not ``m n^2``). ``_gram_lower``: the lower triangle of
``M^T M`` by blocks.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .cholesky import _KIND_D, _NOTRANS, _TRANS, _xxgemm
from .model import NNZ
from .rows import _mirror_lower

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")

SOLVE_BLOCK = 32  # past this size, triangular solves and Gram products run by blocks (BLAS on the blocks)
LARGE_N = 64  # past this size the update takes its large-n path (core.kernels.update's docstring)
INFO_BLOCK = 16  # the strips of rows of A in _whiten_information


@njit(**_JIT)
def _whiten(hx, Hval, cols, yb, rws, L, Hw, rw, A, g):
    """``Hw = R^-1/2 H L``, ``rw = R^-1/2 (y - h)``, ``g = Hw^T rw``, ``A = I + Hw^T Hw`` (full, symmetric).

    Row by row: ``Hw[r] = sum_k H[r, c_k] L[c_k, :c_k+1]`` (``L`` lower triangular; its rows
    past ``n``, those of virtual columns, ``_with_virtual``, are read in full), added to ``g`` times
    ``rw[r]`` while in cache (not by a BLAS ``gemv`` call after, which reads ``Hw`` again); then ``A = I + Hw^T Hw`` by BLAS (``np.dot``), its lower triangle mirrored (exactly
    symmetric). Two consecutive rows that see the same columns (a feature's) are formed in one
    pass, each entry of ``L`` read once for both (the same numbers: a row's group of four columns whose values are all zero, which a row alone
    skips, adds exact zeros to it, ``L`` being finite).
    """
    m, n = Hw.shape
    for j in range(n):
        g[j] = 0.0
    r = 0
    while r < m:
        # two rows at once where they see the same columns (a feature's rows): each row of L read once for both
        two = r + 1 < m
        if two:
            for k in range(NNZ):
                if cols[r, k] != cols[r + 1, k]:
                    two = False
                    break
        for q in range(r, r + 2 if two else r + 1):
            rw[q] = (yb[q] - hx[q]) * rws[q]
            for j in range(n):
                Hw[q, j] = 0.0
        u = r + 1 if two else r
        s, t = rws[r], rws[u]
        for k in range(0, NNZ, 4):  # four columns of H per pass (L[c, j] = 0 past j = c)
            h0, h1, h2, h3 = Hval[r, k] * s, Hval[r, k + 1] * s, Hval[r, k + 2] * s, Hval[r, k + 3] * s
            e0, e1, e2, e3 = Hval[u, k] * t, Hval[u, k + 1] * t, Hval[u, k + 2] * t, Hval[u, k + 3] * t
            hr = h0 != 0.0 or h1 != 0.0 or h2 != 0.0 or h3 != 0.0
            hu = two and (e0 != 0.0 or e1 != 0.0 or e2 != 0.0 or e3 != 0.0)
            if hr or hu:
                c0, c1, c2, c3 = cols[r, k], cols[r, k + 1], cols[r, k + 2], cols[r, k + 3]
                top = min(max(max(c0, c1), max(c2, c3)) + 1, n)
                if hu:
                    for j in range(top):
                        l0, l1, l2, l3 = L[c0, j], L[c1, j], L[c2, j], L[c3, j]
                        Hw[r, j] += (h0 * l0 + h1 * l1) + (h2 * l2 + h3 * l3)
                        Hw[u, j] += (e0 * l0 + e1 * l1) + (e2 * l2 + e3 * l3)
                else:
                    for j in range(top):
                        Hw[r, j] += (h0 * L[c0, j] + h1 * L[c1, j]) + (h2 * L[c2, j] + h3 * L[c3, j])
        for q in range(r, u + 1):
            c = rw[q]
            for j in range(n):
                g[j] += c * Hw[q, j]
        r = u + 1
    _gram_lower(Hw, A)
    for i in range(n):
        A[i, i] += 1.0
    _mirror_lower(A)


@njit(**_JIT)
def _whiten_g(hx, Hval, cols, yb, rws, L, Hw, rw, A, g, ws, wi, upper):
    """``_whiten`` and ``g = Hw^T rw`` up to ``LARGE_N`` columns; past it ``_whiten_information`` (the same numbers
    to round-off; ``ws``, ``wi``: its scratch, ``scratch_sizes``; ``upper``: as there; ``Hw`` is not written).
    The aligned chart's large ``n`` comes here in centred coordinates (``centred._centered_model_rows``)."""
    if A.shape[0] <= LARGE_N:
        _whiten(hx, Hval, cols, yb, rws, L, Hw, rw, A, g)
    else:
        _whiten_information(hx, Hval, cols, yb, rws, L, rw, A, g, ws, wi, upper)


@njit(**_JIT)
def scratch_sizes(n, nv):
    """The float and integer scratch lengths of ``_whiten_g`` for ``n`` columns and ``nv`` virtual ones (those of
    ``_whiten_information``: ``Y``, ``W``, ``Hw^T rw``'s sparse part, a row's non-zeros, two BLAS scalars)."""
    k = n + nv
    return k * k + k * n + k + NNZ + 2, NNZ


@njit(**_JIT)
def _information_rows(hx, Hval, cols, yb, rws, rw, Y, gy, hv, cv):
    """``rw = R^-1/2 (y - h)``, the information ``Y = H^T R^-1 H`` (full, symmetric) and ``gy = H^T R^-1 (y - h)`` of
    the row-sparse ``H``: each row adds the outer product of its non-zero whitened values at their columns."""
    K = Y.shape[0]
    for i in range(K):
        gy[i] = 0.0
        for j in range(K):
            Y[i, j] = 0.0
    for r in range(Hval.shape[0]):
        s = rws[r]
        rw[r] = (yb[r] - hx[r]) * s
        k = 0
        for q in range(NNZ):
            h = Hval[r, q]
            if h != 0.0:
                hv[k] = h * s
                cv[k] = cols[r, q]
                k += 1
        for a in range(k):
            ca, ha = cv[a], hv[a]
            gy[ca] += ha * rw[r]
            for b in range(k):
                Y[ca, cv[b]] += ha * hv[b]


@njit(**_JIT)
def _whiten_information(hx, Hval, cols, yb, rws, L, rw, A, g, ws, wi, upper):
    """``A = I + Hw^T Hw`` and ``g = Hw^T rw`` for a large ``n`` from the information ``Y = H^T R^-1 H``:

        ``A = I + L^T Y L``, ``g = L^T H^T R^-1 (y - h)``   (``Hw = R^-1/2 H L``).

    ``L`` (``(n + nv, n)``): the lower triangular factor, then (the aligned chart's centred coordinates) ``nv``
    dense rows of virtual columns. A feature's rows see the common columns and its own point's, so ``Y`` is an
    arrow: dense on the common columns, 3 x 3 blocks on the points (``_information_rows``, ``m NNZ^2`` products).
    ``W = Y L`` takes, for each non-zero ``Y[i, c]``, row ``c`` of ``L`` up to its diagonal (or whole, a virtual
    row): the dense common rows cost ``n^2 / 2`` each, a point's rows a few short rows. ``L^T W`` is formed
    by strips of ``INFO_BLOCK`` rows of ``A``: strip ``[i0, i1)`` is ``L[i0:, i0:i1]^T W[i0:, :i1]`` (the rows of
    ``L`` that are non-zero there: one BLAS ``gemm``), about ``n^3 / 6`` products in all. The row-by-row
    whitening's Gram product ``Hw^T Hw`` costs ``m n^2 / 2`` less its zeros; here nothing grows with ``m`` but
    ``Y``, which is why this path follows the structure as ``N`` grows.

    Rounding: a whitened row much smaller than its terms (a measured combination of well-known parts with large,
    correlated prior errors) cancels in ``Hw``, and ``Y`` squares that cancellation: ``A``'s error grows with
    its square instead of its first power (the aligned chart's unmeasured centroid, the largest of them, is
    whitened in centred coordinates: ``centred``). On configs/mission-realistic.yaml's updates ``P+`` moved by about
    ``1e-12`` of its standard deviations against an extended-precision reference (the row-by-row form: ``1e-15``),
    far below any statistic; the agreement tests with the numpy update bound it at ``1e-10``.

    ``ws``, ``wi``: scratch of ``scratch_sizes(n, nv)``. With ``upper``, ``A`` is exactly symmetric (lower
    triangle mirrored); without, only the lower triangle and the strips' diagonal blocks are written (an EKF
    step reads no other: ``triangular._factor``).
    """
    K, n = L.shape
    o = 0
    Y = ws[o : o + K * K].reshape((K, K))
    o += K * K
    W = ws[o : o + K * n].reshape((K, n))
    o += K * n
    gy = ws[o : o + K]
    o += K
    hv = ws[o : o + NNZ]
    ab = ws[o + NNZ : o + NNZ + 2]  # alpha = 1, beta = 0 (BLAS reads them through pointers)
    _information_rows(hx, Hval, cols, yb, rws, rw, Y, gy, hv, wi[:NNZ])
    # W = Y L over the non-zeros of Y (row c of L: zero past its diagonal; a virtual row: dense)
    for i in range(K):
        for j in range(n):
            W[i, j] = 0.0
        for c in range(K):
            y = Y[i, c]
            if y != 0.0:
                top = c + 1 if c < n else n
                for j in range(top):
                    W[i, j] += y * L[c, j]
    # the lower triangle of L^T W by strips; column-major: (A^T)[:i1, i0:i1] = (W^T)[:i1, i0:] L[i0:, i0:i1]
    ab[0] = 1.0
    ab[1] = 0.0
    nb = INFO_BLOCK
    for i0 in range(0, n, nb):
        i1 = min(i0 + nb, n)
        _xxgemm(_KIND_D, _NOTRANS, _TRANS, i1, i1 - i0, K - i0, ab[0:1].ctypes, W[i0, :].ctypes, n,
                L[i0, i0:].ctypes, n, ab[1:2].ctypes, A[i0, :].ctypes, n)  # fmt: skip
    for j in range(n):  # g = L^T gy by rows of L (row c: zero past its diagonal; a virtual row: dense)
        g[j] = 0.0
    for c in range(K):
        t = gy[c]
        if t != 0.0:
            for j in range(c + 1 if c < n else n):
                g[j] += t * L[c, j]
    for i in range(n):
        A[i, i] += 1.0
    if upper:
        _mirror_lower(A)


@njit(**_JIT)
def _gram_lower(M, G):
    """The lower triangle of ``G = M^T M`` (``M (m, n)``) by BLAS: one product up to ``SOLVE_BLOCK`` columns,
    else the blocks on and below the diagonal only (about half the flops of the full product)."""
    m, n = M.shape
    nb = SOLVE_BLOCK
    if n <= nb:
        np.dot(M.T, M, G)
        return
    MT = np.ascontiguousarray(M.T)
    tmp = np.empty((nb, nb))
    for i0 in range(0, n, nb):
        i1 = min(i0 + nb, n)
        for j0 in range(0, i0 + 1, nb):
            j1 = min(j0 + nb, n)
            t = tmp[: i1 - i0, : j1 - j0]
            if i1 - i0 == nb and j1 - j0 == nb:
                np.dot(MT[i0:i1], MT[j0:j1].T, tmp)
            else:
                t2 = np.empty((i1 - i0, j1 - j0))
                np.dot(MT[i0:i1], MT[j0:j1].T, t2)
                t = t2
            for i in range(i0, i1):
                for j in range(j0, min(j1, i + 1)):
                    G[i, j] = t[i - i0, j - j0]
