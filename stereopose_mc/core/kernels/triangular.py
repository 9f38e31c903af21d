"""The update's whitened system ``A = I + Hw^T Hw`` factorized in reverse order, and what comes with it.

``_factor`` gives ``A = U U^T`` with ``U`` upper triangular (the Cholesky factor of ``J A J``, ``J`` the reversal of
the indices); ``_solve`` solves ``A z = b`` from it; ``_posterior_covariance_rev`` forms ``P+ = L A^-1 L^T = M M^T``
with ``M = L U^-T`` lower triangular, whose rows are ``P+``'s own square root (the NEES reuse it instead of
factorizing ``P+`` again: ``core.kernels.consistency``). Twins: ``numpy.linalg.cholesky`` and
``scipy.linalg.solve_triangular`` on the dense matrices (``tests/core/test_kernels.py``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .cholesky import _KIND_D, _NOTRANS, _TRANS, _UPLO_U, _chol_solve, _cholesky_t, _potrf, _xxgemm
from .rows import _combine_rows, _mirror_lower, _ptr
from .whiten import LARGE_N

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")

REV_BLOCK = 16  # the blocks of _posterior_covariance_rev
REV_BLOCK_SMALL = 8  # its blocks up to 32 columns (case B's sizes): the fastest measured there


@njit(**_JIT)
def _factor(A, LA):
    """The Cholesky factor of ``A`` in reverse order: ``LA`` lower with ``LA LA^T = J A J`` (``J`` the reversal of
    the indices), i.e. ``A = U U^T`` with ``U = J LA J`` upper triangular (``_solve``; ``P+ = L A^-1 L^T = M M^T``
    with ``M = L U^-T`` lower triangular, ``_posterior_covariance_rev``, whose square root the NEES reuse). Only the
    lower triangle of ``A`` is read, as by ``_cholesky``. False if ``A`` is not positive definite.

    Up to ``LARGE_N`` columns ``J A J``'s lower triangle is copied to ``LA`` and factorized in place as by
    ``_cholesky`` (no transposition after); past it by ``_cholesky_t`` (``cholesky._upper_blocked``).
    """
    n = A.shape[0]
    if n > LARGE_N:
        return _cholesky_t(A, LA, True)
    for i in range(n):  # (J A J)[i, j] = A[n-1-j, n-1-i] for j <= i: the lower triangle of A
        for j in range(i + 1):
            LA[i, j] = A[n - 1 - j, n - 1 - i]
        for j in range(i + 1, n):
            LA[i, j] = 0.0
    return _potrf(LA, _UPLO_U)


@njit(**_JIT)
def _solve(LA, b):
    """``b <- A^-1 b`` from ``_factor``'s ``LA`` (``A^-1 = J (LA LA^T)^-1 J``)."""
    n = b.shape[0]
    for i in range(n // 2):
        b[i], b[n - 1 - i] = b[n - 1 - i], b[i]
    _chol_solve(LA, b)
    for i in range(n // 2):
        b[i], b[n - 1 - i] = b[n - 1 - i], b[i]


@njit(**_JIT)
def _posterior_covariance_rev(L, LA, out, W):
    """``out = L A^-1 L^T`` with ``A`` factorized in reverse order (``_factor``: ``A = U U^T``, ``U`` upper).

    ``L A^-1 L^T = M M^T`` with ``M = L U^-T`` lower triangular (a lower times a lower), about a
    third of the flops of a full ``X = LA^-1 L^T`` and ``X^T X``. With ``U = J LA J``:
    ``M J = Q LA^-T``, ``Q = L J``; ``W = (M J)^T`` solves ``LA W = Q^T`` (forward substitution by
    rows, blocked: a block of rows first takes off the rows solved before it by one BLAS product,
    then solves its own triangle row by row), and row ``j`` of ``W`` is zero left of column
    ``n - 1 - j`` (``W[j, i] = M[i, n - 1 - j]``), which the products skip: each BLAS ``gemm`` on a
    block of ``REV_BLOCK`` rows of ``W`` runs over the columns that block reaches. Then
    ``out = W^T W`` by strips of ``REV_BLOCK`` rows the same way, lower triangle mirrored:
    exactly symmetric. (Blocks of ``REV_BLOCK_SMALL`` rows up to 32 columns.)
    """
    n = L.shape[0]
    nb = REV_BLOCK_SMALL if n <= 32 else REV_BLOCK
    ab = np.empty(3)
    ab[0], ab[1], ab[2] = -1.0, 1.0, 0.0
    for j0 in range(0, n, nb):
        j1 = min(j0 + nb, n)
        for j in range(j0, j1):
            lo = n - 1 - j
            for i in range(lo):
                W[j, i] = 0.0
            for i in range(lo, n):
                W[j, i] = L[i, lo]
        # W[j0:j1] -= LA[j0:j1, k0:k1] W[k0:k1] by blocks of rows k0:k1 above, each over its columns n - k1:
        # (column-major: W^T[c:, j0:j1] -= W^T[c:, k0:k1] LA^T[k0:k1, j0:j1], c = n - k1)
        for k0 in range(0, j0, nb):
            k1 = min(k0 + nb, j0)
            c = n - k1
            _xxgemm(_KIND_D, _NOTRANS, _NOTRANS, k1, j1 - j0, k1 - k0, _ptr(ab, 0), _ptr(W, k0 * n + c), n,
                    _ptr(LA, j0 * n + k0), n, _ptr(ab, 1), _ptr(W, j0 * n + c), n)  # fmt: skip
        for j in range(j0, j1):
            lo = n - 1 - j
            _combine_rows(W, j, lo, n, W, LA, j, j0, j, -1.0)
            r = 1.0 / LA[j, j]  # (a product by the reciprocal: one division per row, not one per entry)
            for i in range(lo, n):
                W[j, i] *= r
    # out[a0:a1, :a1] = sum over the rows r of W that reach column a1 - 1 (r >= n - a1) of W[r, a0:a1]^T W[r, :a1],
    # by blocks of rows r0:r1, each over the columns n - r1: (the others are zero there)
    for a0 in range(0, n, nb):
        a1 = min(a0 + nb, n)
        for i in range(a0, a1):
            for j in range(a1):
                out[i, j] = 0.0
        r1 = n
        while r1 > n - a1:
            r0 = max(r1 - nb, n - a1)
            c = n - r1
            _xxgemm(_KIND_D, _NOTRANS, _TRANS, a1 - c, a1 - a0, r1 - r0, _ptr(ab, 1), _ptr(W, r0 * n + c), n,
                    _ptr(W, r0 * n + a0), n, _ptr(ab, 1), _ptr(out, a0 * n + c), n)  # fmt: skip
            r1 = r0
    _mirror_lower(out)
