"""Whitening of the measurement rows for the compiled updates: ``Hw = R^-1/2 H L``, ``rw``, ``g`` and ``A``.

Twins of the whitened algebra in ``core.kalman.iekf_update``: with ``P = L L^T``, ``Hw = R^-1/2 H L``,
``rw = R^-1/2 (y - h)``, ``g = Hw^T rw`` and ``A = I + Hw^T Hw`` (the system both the EKF and the IEKF solve,
``core.kernels.update``). ``H`` is row-sparse (``model.NNZ`` values per row and their columns), so a row of
``Hw`` is a sum of a few rows of ``L``. ``_whiten`` forms them two rows at a time up to ``LARGE_N`` columns;
``_whiten_staircase`` past it skips the zeros of ``Hw`` that ``L``'s triangle leaves (a staircase) and forms the
Gram product by strips (BLAS on sub-matrices). ``_gram_lower``: the lower triangle of ``M^T M`` by blocks.
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
STAIR_BLOCK = 8  # the strips of rows of A in _whiten_staircase


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
    """``_whiten`` and ``g = Hw^T rw``; past ``LARGE_N`` columns by ``_whiten_staircase`` (the same numbers to
    round-off; ``ws (7 m + 16 n + 14)``, ``wi (2 m + n + 1)``: its float and integer scratch; ``upper``: as there)."""
    if Hw.shape[1] <= LARGE_N:  # (the aligned chart's large n: _centered_model_rows, then _whiten_staircase)
        _whiten(hx, Hval, cols, yb, rws, L, Hw, rw, A, g)
    else:
        _whiten_staircase(hx, Hval, cols, yb, rws, L, Hw, rw, A, g, ws, wi, upper)


@njit(**_JIT)
def _own(h, c, n, Bv, r):
    """An entry ``h`` of a whitened row in column ``c``: ``(h, c)`` if ``c`` is a column of the state, else (a
    virtual column) ``h`` is added to ``Bv[r, c - n]`` and ``(0, 0)`` returned; ``(0, 0)`` for a zero entry."""
    if h == 0.0:
        return 0.0, 0
    if c >= n:
        Bv[r, c - n] += h
        return 0.0, 0
    return h, c


@njit(**_JIT)
def _whiten_staircase(hx, Hval, cols, yb, rws, L, Hs, rw, A, g, ws, wi, upper):
    """``_whiten`` and ``g = Hw^T rw`` for a large ``n``, skipping the exact zeros of ``Hw = R^-1/2 H L``.

    A row of ``H`` whose last non-zero column is ``c`` gives a row of ``Hw`` that is zero past
    ``c`` (``L`` is lower triangular), and a feature's row sees only the 12 common columns and
    its own point's: its ``Hw`` row stops at its point (a staircase). In the aligned chart a row
    may also have 3 virtual columns, whose rows ``V = L[n:n+3]`` are dense; they are split off:
    ``Hw = Hs + Bv V`` with ``Hs`` the staircase part and ``Bv (m, 3)`` the virtual coefficients, and

        ``Hw^T Hw = Hs^T Hs + W V + V^T W^T``, ``W = Hs^T Bv + V^T E / 2``, ``E = Bv^T Bv``;
        ``g = Hs^T rw + V^T (Bv^T rw)``.

    ``Hs`` is stored with its rows sorted by their length, shortest first (a stable counting
    sort: the features stay in their order, the pseudo rows, whose ``k`` columns are last, stay
    last, and so the sums run in the order of the dense product, small terms first), and
    ``Hs^T Hs`` is formed by strips of ``STAIR_BLOCK`` rows of ``A``: strip ``[i0, i1)`` is
    ``Hs[r0:, i0:i1]^T Hs[r0:, :i1]`` over the rows ``r0:`` that reach column ``i0`` (one BLAS
    ``gemm`` on the sub-matrices in place), about half the full Gram product's flops at
    ``N = 40``. ``(g, Hs^T Bv)`` is one ``gemm`` too, the rank-6 term another. With ``upper``, ``A`` is exactly
    symmetric (lower triangle mirrored); without, only its lower triangle is written (an EKF step reads no other:
    ``_factor``; the mirror is a small part of the update).

    The split squares any cancellation between ``Hs`` and ``Bv V``: the aligned chart's virtual
    columns (every point, for the centroid) are therefore not split here but whitened in the
    centered coordinates (``_centered_model_rows``), where only the last point's rows keep a
    virtual column, of small rows.
    """
    m, n = Hs.shape
    nv = L.shape[0] - n  # virtual columns (3 in the aligned chart, else 0)
    Bv = ws[: 3 * m].reshape((m, 3))
    Z = ws[3 * m : 7 * m].reshape((m, 4))
    o = 7 * m
    GC = ws[o : o + 4 * n].reshape((n, 4))  # (g, Cv): g = Hs^T rw, Cv = Hs^T Bv
    o += 4 * n
    U1 = ws[o : o + 6 * n].reshape((n, 6))
    U2 = ws[o + 6 * n : o + 12 * n].reshape((6, n))
    o += 12 * n
    E = ws[o : o + 9].reshape((3, 3))
    bw = ws[o + 9 : o + 12]
    ab = ws[o + 12 : o + 14]  # alpha = 1, beta (BLAS reads them through pointers)
    ext = wi[:m]
    pos = wi[m : 2 * m]
    count = wi[2 * m : 2 * m + n + 1]
    # --- each row's length (last own non-zero column + 1) and its place, shortest first (stable)
    for e in range(n + 1):
        count[e] = 0
    for r in range(m):
        last = -1
        for k in range(NNZ):
            c = cols[r, k]
            if Hval[r, k] != 0.0 and c < n and c > last:
                last = c
        ext[r] = last + 1
        count[last + 1] += 1
    start = 0
    for e in range(n + 1):  # count[e] <- first position of the rows of length e
        c = count[e]
        count[e] = start
        start += c
    for r in range(m):
        pos[r] = count[ext[r]]
        count[ext[r]] += 1
    # count[e] is now the first position of the rows longer than e: rows count[e]: reach column e
    # --- the rows: Hs[pos[r]] = sum of the own columns' rows of L (four per pass); Bv; rw; Z[pos[r]] = (rw, Bv)
    for r in range(m):
        s = rws[r]
        rw[r] = (yb[r] - hx[r]) * s
        p = pos[r]
        for j in range(n):
            Hs[p, j] = 0.0
        Bv[r, 0] = 0.0
        Bv[r, 1] = 0.0
        Bv[r, 2] = 0.0
        for k in range(0, NNZ, 4):
            h0, c0 = _own(Hval[r, k] * s, cols[r, k], n, Bv, r)
            h1, c1 = _own(Hval[r, k + 1] * s, cols[r, k + 1], n, Bv, r)
            h2, c2 = _own(Hval[r, k + 2] * s, cols[r, k + 2], n, Bv, r)
            h3, c3 = _own(Hval[r, k + 3] * s, cols[r, k + 3], n, Bv, r)
            top = max(max(c0, c1), max(c2, c3)) + 1
            if h0 != 0.0 or h1 != 0.0 or h2 != 0.0 or h3 != 0.0:
                for j in range(top):
                    Hs[p, j] += (h0 * L[c0, j] + h1 * L[c1, j]) + (h2 * L[c2, j] + h3 * L[c3, j])
        Z[p, 0] = rw[r]
        Z[p, 1] = Bv[r, 0]
        Z[p, 2] = Bv[r, 1]
        Z[p, 3] = Bv[r, 2]
    # (g, Cv) = Hs^T Z over the rows of any length (one gemm; column-major GC^T = Z^T Hs)
    ab[0] = 1.0
    ab[1] = 0.0
    r0 = count[0]
    c = m - r0
    if c > 0:
        _xxgemm(_KIND_D, _NOTRANS, _TRANS, 4, n, c, ab[0:1].ctypes, Z[r0, :].ctypes, 4, Hs[r0, :].ctypes, n,
                ab[1:2].ctypes, GC.ctypes, 4)  # fmt: skip
    else:
        GC[:, :] = 0.0
    for a in range(3):
        t = 0.0
        for r in range(m):
            t += Bv[r, a] * rw[r]
        bw[a] = t
    # --- the lower triangle of Hs^T Hs by strips of rows of A, each over the rows that reach it
    nb = STAIR_BLOCK
    for i0 in range(0, n, nb):
        i1 = min(i0 + nb, n)
        r0 = count[i0]  # the rows from r0 on reach column i0
        c = m - r0
        if c == 0:
            for i in range(i0, i1):
                for j in range(i1):
                    A[i, j] = 0.0
            continue
        # column-major view: Hs^T (n x m, ld n); A[i0:i1, :i1] is (A^T)[:i1, i0:i1] (ld n)
        _xxgemm(_KIND_D, _NOTRANS, _TRANS, i1, i1 - i0, c, ab[0:1].ctypes, Hs[r0, :].ctypes, n, Hs[r0, i0:].ctypes,
                n, ab[1:2].ctypes, A[i0, :].ctypes, n)  # fmt: skip
    # --- the virtual columns: + W V + V^T W^T and g += V^T (Bv^T rw)
    if nv == 0:
        for j in range(n):
            g[j] = GC[j, 0]
    else:
        for a in range(3):
            for b in range(3):
                t = 0.0
                for r in range(m):
                    t += Bv[r, a] * Bv[r, b]
                E[a, b] = t
        for j in range(n):
            for a in range(3):
                t = GC[j, 1 + a] + 0.5 * (L[n, j] * E[0, a] + L[n + 1, j] * E[1, a] + L[n + 2, j] * E[2, a])
                U1[j, a] = t
                U2[3 + a, j] = t
                U1[j, 3 + a] = L[n + a, j]
                U2[a, j] = L[n + a, j]
            g[j] = GC[j, 0] + (L[n, j] * bw[0] + L[n + 1, j] * bw[1] + L[n + 2, j] * bw[2])
        ab[1] = 1.0
        # A += U1 U2 (C order): column-major A^T += U2^T U1^T
        _xxgemm(_KIND_D, _NOTRANS, _NOTRANS, n, n, 6, ab[0:1].ctypes, U2.ctypes, n, U1.ctypes, 6, ab[1:2].ctypes,
                A.ctypes, n)  # fmt: skip
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
