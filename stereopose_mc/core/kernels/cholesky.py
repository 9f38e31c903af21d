"""Cholesky factorizations and triangular solves of the compiled kernels (Numba), one small matrix at a time.

``_cholesky`` (LAPACK's ``potrf`` in place), its transposed layout ``_cholesky_t`` (the update's large ``n``: by
``_upper_blocked``, blocks of rows around BLAS products),
``_cholesky_upper`` (the NEES's own factor of ``P``), ``_cholesky_small`` (written out, for the NEES's small
blocks), ``_forward`` (forward substitution) and ``_chol_solve`` (``(L L^T)^-1 b``). Shared by ``core.kernels.update`` and
``core.kernels.consistency`` (and ``core.kernels.triangular``, the update's reverse-order factorization), which
the update calls in turn for the NEES of its posteriors (this module imports none of them).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types

from .rows import _combine_rows, _dot_row, _ptr

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")

# LAPACK's dpotrf as Numba's own ``np.linalg.cholesky`` calls it (its C helper resolves scipy's
# ``cython_lapack`` at run time, so a cached kernel stays valid in a new process); called directly
# it factorizes in place: no copy of the input, no allocated output, no exception to catch.
_xxpotrf = types.ExternalFunction("numba_xxpotrf", types.intc(types.char, types.char, types.intp,
                                                               types.CPointer(types.float64), types.intp))  # fmt: skip
_KIND_D, _UPLO_U, _UPLO_L = 100, 85, 76  # ord("d") (float64), ord("U"), ord("L")

# BLAS's dgemm as Numba's own ``np.dot`` calls it (resolved at run time like ``_xxpotrf`` below), called directly for
# products of sub-matrices given by a first element and a leading dimension (column-major, as BLAS sees a C-order
# matrix: transposed), with ``beta``
_xxgemm = types.ExternalFunction("numba_xxgemm", types.intc(
    types.char, types.char, types.char, types.intp, types.intp, types.intp, types.CPointer(types.float64),
    types.CPointer(types.float64), types.intp, types.CPointer(types.float64), types.intp,
    types.CPointer(types.float64), types.CPointer(types.float64), types.intp))  # fmt: skip
_NOTRANS, _TRANS = 110, 116  # ord("n"), ord("t")

# _upper_blocked's blocks: a BLAS product takes off the rows above a block of CHOL_BLOCK rows, then one per CHOL_ROWS
# rows inside it takes off those of the block above them, and each row its own pair's (8 / 2: the fastest measured on
# the large path's sizes, benchmarks/kernels_bench.py)
CHOL_BLOCK = 8
CHOL_ROWS = 2


@njit(**_JIT)
def _cholesky(A, L):
    """Lower ``L`` with ``L L^T = A`` (only the lower triangle of ``A`` is read); False if not PD.

    LAPACK's ``potrf`` on ``L`` in place (``L`` may be a block ``M[:m, :m]`` of a larger C-order
    array): a C-order lower triangle is the upper triangle of the same memory read in Fortran
    order, hence ``uplo = "U"``. ``potrf`` fails (``info > 0``) on a matrix that is not positive
    definite or meets a NaN pivot; an infinite pivot is caught by the check of the diagonal.
    """
    n = A.shape[0]
    for i in range(n):
        for j in range(i + 1):
            L[i, j] = A[i, j]
        for j in range(i + 1, n):
            L[i, j] = 0.0
    return _potrf(L, _UPLO_U)


@njit(**_JIT)
def _potrf(L, uplo):
    """LAPACK's ``potrf`` on ``L`` in place, as column-major memory (``uplo``: which triangle of it holds the
    matrix, the other being zeros); False if it fails or a pivot is not finite."""
    n = L.shape[0]
    if n == 0:
        return True
    if L.strides[1] == 8:  # unit-stride rows: in place; a block ``L[:m, :m]``'s row stride is the leading dimension
        info = _xxpotrf(_KIND_D, uplo, n, L.ctypes, L.strides[0] // 8)
    else:  # (never in these kernels) a contiguous copy; no recursive call: a cached recursion does not link
        Lc = np.ascontiguousarray(L)
        info = _xxpotrf(_KIND_D, uplo, n, Lc.ctypes, n)
        L[:, :] = Lc
    if info != 0:
        return False
    for i in range(n):
        if not math.isfinite(L[i, i]):
            return False
    return True


@njit(**_JIT)
def _cholesky_t(A, L, rev):
    """``_cholesky`` for the large-``n`` path (``_factor``, a full-state ``P-``): the lower triangle of ``A`` (with
    ``rev``: of ``J A J``) goes to the upper triangle of ``L``, which ``_cholesky_tu`` factorizes in place. False if
    ``A`` is not positive definite."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i):
            L[i, j] = 0.0
        if rev:  # (J A J)[j, i] = A[n-1-j, n-1-i] = A[n-1-i, n-1-j] (j >= i): from the lower triangle
            for j in range(i, n):
                L[i, j] = A[n - 1 - i, n - 1 - j]
        else:
            for j in range(i, n):
                L[i, j] = A[j, i]
    return _cholesky_tu(L)


@njit(**_JIT)
def _cholesky_tu(L):
    """``_cholesky`` in place from the upper triangle of ``L`` (C order): ``_upper_blocked``'s factor ``U`` (``U^T U``
    the matrix), transposed to the lower triangle, zeros above. Reads only the upper triangle (``_cholesky_t``'s copy,
    or ``update._center_cov``'s matrix, whose two triangles are both computed: symmetric to round-off, either as
    good). False if it is not positive definite."""
    if not _upper_blocked(L):
        return False
    n = L.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            L[j, i] = L[i, j]
            L[i, j] = 0.0
    return True


@njit(**_JIT)
def _upper_blocked(U):
    """Upper ``U`` with ``U^T U = A`` in place, ``A`` given by the upper triangle of ``U`` (C order; the entries below
    the diagonal are left undefined: ``_cholesky_tu`` overwrites them), by blocks of rows for the large ``n`` of the
    update (74-134 columns); False if ``A`` is not positive definite (a pivot not > 0 or not finite, NaN included).

    Row ``j`` of ``U`` is ``(A[j, j:] - sum_{k<j} U[k, j] U[k, j:]) / sqrt(pivot)`` (``_upper_rows``). By blocks:
    a block of ``CHOL_BLOCK`` rows first takes off all the rows above it by one BLAS product (``U[j0:j1, j0:] -=
    U[:j0, j0:j1]^T U[:j0, j0:]``, column-major: ``U^T[j0:, j0:j1] -= U^T[j0:, :j0] U[:j0, j0:j1]``), within it each
    pair of rows (``CHOL_ROWS``) the block's rows above it the same way, and each row its pair's first row
    (``rows._combine_rows``): faster than LAPACK's (OpenBLAS's) ``potrf`` on the large path's sizes, its numbers
    to round-off (``potrf`` blocks likewise, by other blocks); ``potrf`` stays below ``LARGE_N``, where the two are
    even. ``U`` must be C-contiguous (the kernels' scratch); any other layout goes to
    ``potrf`` (the same factor)."""
    n = U.shape[0]
    if n == 0 or U.strides[1] != 8 or U.strides[0] != 8 * n:
        return _potrf(U, _UPLO_L)
    ab = np.empty(2)
    ab[0], ab[1] = -1.0, 1.0
    UT = U.T
    for b0 in range(0, n, CHOL_BLOCK):
        b1 = min(b0 + CHOL_BLOCK, n)
        if b0 > 0:
            _xxgemm(_KIND_D, _NOTRANS, _TRANS, n - b0, b1 - b0, b0, _ptr(ab, 0), _ptr(U, b0), n, _ptr(U, b0), n,
                    _ptr(ab, 1), _ptr(U, b0 * n + b0), n)  # fmt: skip
        for j0 in range(b0, b1, CHOL_ROWS):
            j1 = min(j0 + CHOL_ROWS, b1)
            if j0 > b0:
                _xxgemm(_KIND_D, _NOTRANS, _TRANS, n - j0, j1 - j0, j0 - b0, _ptr(ab, 0), _ptr(U, b0 * n + j0), n,
                        _ptr(U, b0 * n + j0), n, _ptr(ab, 1), _ptr(U, j0 * n + j0), n)  # fmt: skip
            for j in range(j0, j1):
                _combine_rows(U, j, j, n, U, UT, j, j0, j, -1.0)
                d = U[j, j]
                if not (d > 0.0 and d < math.inf):
                    return False
                r = 1.0 / math.sqrt(d)
                for c in range(j, n):
                    U[j, c] *= r
    return True


@njit(**_JIT)
def _cholesky_upper(A, U):
    """Upper ``U`` with ``U^T U = A`` (only the lower triangle of ``A`` is read); False if not PD.

    ``potrf`` with ``uplo = "L"`` on ``U`` as column-major memory, where the C-order upper triangle
    is the lower one: the factor ``U = L^T`` of ``_cholesky``, whose rows in reverse order the NEES read
    (``core.kernels.consistency``), as they read the compiled update's ``R+``.
    """
    _lower_to_upper(A, U)
    return _potrf(U, _UPLO_L)


@njit(**_JIT)
def _lower_to_upper(A, U):
    """``U``'s upper triangle = the transpose of ``A``'s lower one, zeros below its diagonal (the start of an upper
    factor ``U^T U = A``: ``_cholesky_upper``, ``_upper_rows``)."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i):
            U[i, j] = 0.0
        for j in range(i, n):
            U[i, j] = A[j, i]


@njit(**_JIT)
def _upper_rows(A, U, recip=True):
    """Upper ``U`` with ``U^T U = A`` (the lower triangle of ``A`` read), row by row: ``U[j, j:] = (A[j:, j] - sum_{k<j}
    U[k, j] U[k, j:]) / sqrt(pivot)``, four rows of ``U`` per pass (``rows._combine_rows``, contiguous); False if
    ``A`` is not positive definite (a pivot not > 0, NaN included). Written out, for small blocks (faster than
    ``potrf`` there, slower past ``consistency.ROWS_MAX``). ``recip``: a row is multiplied by the reciprocal
    of its pivot's square root; else divided by it (``_cholesky_small``'s numbers, which the NEES's scalar 2 x 2 and
    3 x 3 blocks repeat bit for bit)."""
    n = A.shape[0]
    _lower_to_upper(A, U)
    UT = U.T
    for j in range(n):
        _combine_rows(U, j, j, n, U, UT, j, 0, j, -1.0)
        d = U[j, j]
        if not d > 0.0:
            return False
        d = math.sqrt(d)
        if recip:
            r = 1.0 / d
            for c in range(j, n):
                U[j, c] *= r
        else:
            for c in range(j, n):
                U[j, c] /= d
    return True


@njit(**_JIT)
def _cholesky_small(A, L):
    """``_cholesky`` written out (left-looking), for the small blocks where LAPACK's call costs more than the work.

    Row ``j`` of ``U = L^T`` (held in the upper triangle of ``L``, transposed at the end) is row
    ``j`` of ``A``'s upper triangle minus a combination of the rows above it, divided by the
    square root of its pivot (``_upper_rows``).
    """
    if not _upper_rows(A, L, False):
        return False
    n = A.shape[0]
    for i in range(n):
        for j in range(i):
            L[i, j] = L[j, i]
            L[j, i] = 0.0
    return True


@njit(**_JIT)
def _forward(L, b, out, lo=0):
    """``out = L^-1 b`` (``L`` lower triangular, forward substitution; ``out`` may be ``b``).

    ``lo``: ``b[:lo]`` is zero, so ``out[:lo]`` is too and the sums start at ``lo`` (the same
    numbers as from 0 when ``lo`` is a multiple of 4: the terms skipped are exact zeros, and
    ``_dot_row``'s four partial sums keep their terms).
    """
    n = L.shape[0]
    for i in range(lo):
        out[i] = 0.0
    for i in range(lo, n):
        if i < 16:  # short rows (the NEES's small blocks): one running sum costs less than four
            t = b[i]
            for k in range(lo, i):
                t -= L[i, k] * out[k]
        else:
            t = b[i] - _dot_row(L, i, out, lo, i)
        out[i] = t / L[i, i]


@njit(**_JIT)
def _chol_solve(L, b):
    """``b <- (L L^T)^-1 b`` in place (``b`` a vector)."""
    n = L.shape[0]
    _forward(L, b, b)
    # L^T x = b from the last row up, by rows of L (contiguous): x_i = b_i / L_ii, then b_k -= L_ik x_i, k < i
    for i in range(n - 1, -1, -1):
        xi = b[i] / L[i, i]
        b[i] = xi
        Li = L[i]
        for k in range(i):
            b[k] -= Li[k] * xi
