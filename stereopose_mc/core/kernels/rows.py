"""Row and dot primitives of the compiled kernels: sums in four chains (two rows per pass where a matrix-vector
product allows), row operations, addresses for BLAS.

Shared by the factorizations (``core.kernels.cholesky``), the whitening (``whiten``), the centred coordinates
(``centred``), the update loop (``update``) and the NEES (``consistency``). Each reads its rows in place (no row
view: a view made inside a compiled function costs an atomic increment and decrement of its owner's reference
count) and sums in a fixed order, so that a trial's result depends on its own inputs only.
"""

from __future__ import annotations

from numba import njit, types
from numba.extending import intrinsic

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")


@njit(**_JIT)
def _mirror_lower(A):
    """Copy the lower triangle of the square ``A`` onto its upper triangle (in place)."""
    n = A.shape[0]
    for i in range(n):
        for j in range(i):
            A[j, i] = A[i, j]


@njit(**_JIT)
def _copy_row(dst, r, src, s, m):
    """``dst[r, :m] = src[s, :m]``, indexed in place (a row view costs an atomic increment and decrement of its
    reference count): a chart map's identity rows (``aligned._apply_error_map``, ``attitude._apply_error_map``)."""
    for c in range(m):
        dst[r, c] = src[s, c]


@njit(**_JIT)
def _combine_rows(O, o, lo, hi, M, Cf, c, k0, k1, sign):
    """``O[o, lo:hi] += sign * sum_{k0 <= k < k1} Cf[c, k] M[k, lo:hi]``, four rows of ``M`` per pass.

    The row operation of the factorizations and triangular solves: contiguous (vectorizable
    without reassociating a sum), and the row ``O[o]`` is read and written a quarter as often as
    with one axpy per row; a group of four zero coefficients is skipped. The rows are indexed in
    place, not passed as views (``O[o]``, ``Cf[c]``): each array view a compiled function makes
    costs an atomic increment and decrement of its reference count, which between the stores of
    a solve's rows cost more than their arithmetic.
    """
    k = k0
    while k + 4 <= k1:
        a0, a1, a2, a3 = sign * Cf[c, k], sign * Cf[c, k + 1], sign * Cf[c, k + 2], sign * Cf[c, k + 3]
        if a0 != 0.0 or a1 != 0.0 or a2 != 0.0 or a3 != 0.0:
            for j in range(lo, hi):
                O[o, j] += (a0 * M[k, j] + a1 * M[k + 1, j]) + (a2 * M[k + 2, j] + a3 * M[k + 3, j])
        k += 4
    while k < k1:
        a = sign * Cf[c, k]
        if a != 0.0:
            for j in range(lo, hi):
                O[o, j] += a * M[k, j]
        k += 1


@intrinsic
def _ptr(typingctx, a, k):
    """The address of element ``k`` of the C-contiguous array ``a`` in flat order (``i * ld + j`` of a matrix),
    for BLAS and LAPACK calls on sub-matrices: not ``a[i, j:].ctypes``, a view whose reference count costs two
    atomic operations per call."""
    sig = types.CPointer(a.dtype)(a, k)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        off = context.cast(builder, args[1], signature.args[1], types.intp)
        return builder.gep(ary.data, [off])

    return sig, codegen


@njit(**_JIT)
def _dot_row(M, i, b, lo, hi):
    """``sum_{lo <= k < hi} M[i, k] b[k]`` in four partial sums, added at the end.

    A single running sum is one chain of dependent additions (each waits for the last: ~4
    cycles per term), which the compiler may not reorder without ``fastmath``; four
    independent chains run ~4x faster at the lengths of these kernels (30-140). The order is
    fixed, so a trial's result does not depend on anything but its own inputs. Reads row ``i``
    in place (no row view to build: this runs once per row of a solve).
    """
    return _chains(M, i, b, lo, hi, 0.0, 0.0, 0.0, 0.0)


@njit(**_JIT)
def _chains(M, i, b, k, hi, s0, s1, s2, s3):
    """``_dot_row``'s four chains ``s0..s3`` carried on from column ``k`` to ``hi`` (term ``k + c`` of each group of
    four into chain ``c``, the last ``< 4`` terms into ``s0``), then added: ``(s0 + s1) + (s2 + s3)``."""
    while k + 4 <= hi:
        s0 += M[i, k] * b[k]
        s1 += M[i, k + 1] * b[k + 1]
        s2 += M[i, k + 2] * b[k + 2]
        s3 += M[i, k + 3] * b[k + 3]
        k += 4
    while k < hi:
        s0 += M[i, k] * b[k]
        k += 1
    return (s0 + s1) + (s2 + s3)


@njit(**_JIT)
def _dot_row_pair(M, i, b, lo, hi_i, hi_j):
    """``(_dot_row(M, i, b, lo, hi_i), _dot_row(M, i + 1, b, lo, hi_j))`` for ``hi_i <= hi_j``: the same two sums in
    the same order (each its own four chains, ``_chains``), in one pass over ``b`` while both rows have a group of
    four left. Eight independent chains instead of four keep both of the core's floating-point adders busy (each
    addition waits ~4 cycles for its chain's last), and each ``b[k]`` is read once for both rows: a matrix-vector
    product by pairs of rows (``update``'s ``A z``, ``centred._lower_mul``'s ``L z``) in less time, the same bits."""
    j = i + 1
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    t0 = 0.0
    t1 = 0.0
    t2 = 0.0
    t3 = 0.0
    k = lo
    while k + 4 <= hi_i:
        b0, b1, b2, b3 = b[k], b[k + 1], b[k + 2], b[k + 3]
        s0 += M[i, k] * b0
        s1 += M[i, k + 1] * b1
        s2 += M[i, k + 2] * b2
        s3 += M[i, k + 3] * b3
        t0 += M[j, k] * b0
        t1 += M[j, k + 1] * b1
        t2 += M[j, k + 2] * b2
        t3 += M[j, k + 3] * b3
        k += 4
    return _chains(M, i, b, k, hi_i, s0, s1, s2, s3), _chains(M, j, b, k, hi_j, t0, t1, t2, t3)


@njit(**_JIT)
def _pair_products(M, v, out, lower):
    """``out = M v`` row by row, ``out[i] = _dot_row(M, i, v, 0, hi)`` (``hi = i + 1`` where ``lower``: ``M`` lower
    triangular; else ``n``), two rows per pass (``_dot_row_pair``: the same sums in the same order)."""
    n = M.shape[0]
    i = 0
    while i + 2 <= n:
        out[i], out[i + 1] = _dot_row_pair(M, i, v, 0, i + 1 if lower else n, i + 2 if lower else n)
        i += 2
    if i < n:
        out[i] = _dot_row(M, i, v, 0, i + 1 if lower else n)


@njit(**_JIT)
def _dot_rows(M, i, V, j, lo, hi):
    """``_dot_row`` of two rows, ``sum_{lo <= k < hi} M[i, k] V[j, k]`` (the same sums in the same order), read in
    place: a row view (``V[j]``) costs an atomic increment and decrement of its reference count."""
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    k = lo
    while k + 4 <= hi:
        s0 += M[i, k] * V[j, k]
        s1 += M[i, k + 1] * V[j, k + 1]
        s2 += M[i, k + 2] * V[j, k + 2]
        s3 += M[i, k + 3] * V[j, k + 3]
        k += 4
    while k < hi:
        s0 += M[i, k] * V[j, k]
        k += 1
    return (s0 + s1) + (s2 + s3)


@njit(**_JIT)
def _dot(a, b, lo, hi):
    """``sum_{lo <= k < hi} a[k] b[k]`` of two vectors: ``_dot_row`` on ``a`` as a one-row matrix."""
    return _dot_row(a.reshape((1, a.shape[0])), 0, b, lo, hi)


@njit(**_JIT)
def _row_nonzeros(Y, nz, cnt):
    """``cnt[r]`` and ``nz[r, :cnt[r]]``: the columns of row ``r`` of ``Y`` that are not zero, in increasing order."""
    for r in range(Y.shape[0]):
        c = 0
        for k in range(Y.shape[1]):
            if Y[r, k] != 0.0:
                nz[r, c] = k
                c += 1
        cnt[r] = c


@njit(**_JIT)
def _sparse_rows_product(Y, nz, cnt, M, O, lower):
    """``O = Y M`` from the non-zeros of ``Y``'s rows (``_row_nonzeros``): ``O[r] = sum_j Y[r, k_j] M[k_j]`` over
    ``k_j = nz[r, j]``, four rows of ``M`` per pass (contiguous, in a fixed order: a trial's bits depend on its
    own inputs only); ``lower``: only the columns ``c <= r`` of each row (a symmetric product mirrored after).

    A row of ``Y`` with ``k`` non-zeros costs ``k`` scaled rows of ``M`` instead of its full length: the
    transition of an error-state chart is the identity but for a few dense rows (``aligned.predict_covariance_batch``).
    """
    for r in range(O.shape[0]):
        m = r + 1 if lower else O.shape[1]
        for c in range(m):
            O[r, c] = 0.0
        j, end = 0, cnt[r]
        while j + 4 <= end:
            k0, k1, k2, k3 = nz[r, j], nz[r, j + 1], nz[r, j + 2], nz[r, j + 3]
            a0, a1, a2, a3 = Y[r, k0], Y[r, k1], Y[r, k2], Y[r, k3]
            for c in range(m):
                O[r, c] += (a0 * M[k0, c] + a1 * M[k1, c]) + (a2 * M[k2, c] + a3 * M[k3, c])
            j += 4
        while j < end:
            k = nz[r, j]
            a = Y[r, k]
            for c in range(m):
                O[r, c] += a * M[k, c]
            j += 1
