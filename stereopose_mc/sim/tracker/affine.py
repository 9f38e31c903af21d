"""Affine Lucas-Kanade refinement of feature windows (inverse compositional; Baker & Matthews 2004).

A template ``T(x)`` (the ``w x w`` window around a feature, ``x`` the offsets from its centre)
is found in an image ``I`` under the warp ``W(x; A, t) = A x + t``: minimize
``sum_x (g I(W(x)) + b - T(x))^2`` over the affine ``A``, ``t`` and a brightness gain and
offset ``g``, ``b`` (solved in closed form each iteration, so a face whose lighting changes
as it turns is still matched). Inverse compositional: the steepest-descent images
``SD = grad T . dW/dp`` with ``dW/dp = [[x, 0, y, 0, 1, 0], [0, x, 0, y, 0, 1]]`` and the
Hessian ``H = SD^T SD`` are computed once per template; each iteration solves
``H dp = SD^T e`` with ``e = g I(W(x)) + b - T(x)`` and composes ``W <- W o W(dp)^-1``.

Why affine: a translation-only window (OpenCV's KLT) tracking a surface whose image is
slowly scaled or sheared (a face turning, the other camera's view of a slanted face) is
biased by the deformation times the offset of the window's texture from its centre; frame
after frame the bias adds up to a drift of tenths of a pixel. Matching against the window
from the detection frame with an affine warp removes the accumulation.

Positions are OpenCV coordinates (pixel centres at integers), batched over features.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates

Array = NDArray[np.float64]
PRIOR = 5.0  # weight of the deformation penalty (see refine)


def offsets(w: int) -> Array:
    """Window offsets ``(w*w, 2)`` as ``(x, y)``, centred on 0."""
    r = (w - 1) / 2.0
    y, x = np.mgrid[0:w, 0:w] - r
    return np.stack([x.ravel(), y.ravel()], axis=-1)


def sample(image: NDArray, pts: Array) -> Array:
    """Bilinear samples of ``image`` at OpenCV positions ``pts (..., 2)``."""
    p = pts.reshape(-1, 2)
    # interpolated in double and rounded to float32 as from a float32 copy of the image; an 8-bit image (a frame) is
    # read as it is: the same numbers, from a quarter of the memory (2x faster on a 1024 px frame)
    src = image if np.can_cast(image.dtype, np.float32) else image.astype(np.float32)
    v = map_coordinates(src, [p[:, 1], p[:, 0]], order=1, mode="nearest", output=np.float32)
    return v.reshape(pts.shape[:-1]).astype(float)


def templates(image: NDArray, centre: Array, w: int) -> tuple[Array, Array]:
    """Templates ``(n, w*w)`` around ``centre (n, 2)`` and their steepest-descent images ``(n, w*w, 6)``."""
    if len(centre) == 0:
        return np.zeros((0, w * w)), np.zeros((0, w * w, 6))
    X = offsets(w + 2)  # one pixel of border for the central differences
    big = sample(image, centre[:, None, :] + X).reshape(-1, w + 2, w + 2)
    gx = 0.5 * (big[:, 1:-1, 2:] - big[:, 1:-1, :-2])
    gy = 0.5 * (big[:, 2:, 1:-1] - big[:, :-2, 1:-1])
    T = big[:, 1:-1, 1:-1].reshape(len(centre), -1)
    gx, gy = gx.reshape(len(centre), -1), gy.reshape(len(centre), -1)
    x, y = offsets(w).T
    SD = np.stack([gx * x, gy * x, gx * y, gy * y, gx, gy], axis=-1)
    return T, SD


def warped(A: Array, t: Array, X: Array) -> Array:
    """The warped offsets ``W(x) = A x + t``, ``(n, m, 2)`` for ``A (n, 2, 2)``, ``t (n, 2)``, ``X (m, 2)``: the two
    products summed as ``einsum("nij,mj->nmi", A, X)`` sums them (the same numbers), without its slow strided loop
    (3x faster at 60 windows of 15 x 15)."""
    return (A[:, None, :, 0] * X[None, :, 0, None] + A[:, None, :, 1] * X[None, :, 1, None]) + t[:, None, :]


def ncc(a: Array, b: Array) -> Array:
    """Zero-mean normalized cross-correlation of rows ``(n, m)``."""
    a = a - a.mean(-1, keepdims=True)
    b = b - b.mean(-1, keepdims=True)
    den = np.sqrt((a * a).sum(-1) * (b * b).sum(-1))
    return np.where(den > 0, (a * b).sum(-1) / np.where(den > 0, den, 1.0), 0.0)


def refine(image: NDArray, T: Array, SD: Array, A: Array, t: Array, w: int, prior: float = PRIOR,
           iterations: int = 30, tol: float = 1e-3) -> tuple[Array, Array, Array]:  # fmt: skip
    """Affine warps ``(A (n, 2, 2), t (n, 2))`` of templates ``T`` in ``image`` from the given start;
    returns the refined ``A``, ``t`` and the NCC of the matched windows.

    The deformation is held to its start ``A0`` by a penalty ``mu |A - A0|_F^2`` with
    ``mu = prior * (H_xx + H_yy) / 2`` (the translation block of ``H``: the window's gradient
    energy), so a window with little texture does not fit noise with a wild affine; in the
    Gauss-Newton step it adds ``mu`` to the deformation block of ``H`` and ``mu (A - A0)`` to
    the right-hand side (``A_new ~ A (1 - dA)``)."""
    if len(T) == 0:
        return A, t, np.zeros(0)
    X = offsets(w)
    H = np.einsum("nmi,nmj->nij", SD, SD) + 1e-9 * np.eye(6)
    mu = prior * 0.5 * (H[:, 4, 4] + H[:, 5, 5])
    H[:, :4, :4] += mu[:, None, None] * np.eye(4)
    A0 = A.copy()
    A, t = A.copy(), t.copy()
    active = np.ones(len(T), bool)
    for _ in range(iterations):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        Iw = sample(image, warped(A[idx], t[idx], X))
        # brightness: g I + b ~ T in least squares
        Im, Tm = Iw.mean(-1, keepdims=True), T[idx].mean(-1, keepdims=True)
        dI = Iw - Im
        g = (dI * (T[idx] - Tm)).sum(-1, keepdims=True) / np.maximum((dI * dI).sum(-1, keepdims=True), 1e-12)
        e = g * dI + Tm - T[idx]
        E = A[idx] - A0[idx]
        rhs = np.einsum("nmi,nm->ni", SD[idx], e)
        rhs[:, :4] += mu[idx, None] * np.stack([E[:, 0, 0], E[:, 1, 0], E[:, 0, 1], E[:, 1, 1]], axis=-1)
        dp = np.linalg.solve(H[idx], rhs[..., None])[..., 0]
        dA = np.stack([[1 + dp[:, 0], dp[:, 2]], [dp[:, 1], 1 + dp[:, 3]]]).transpose(2, 0, 1)
        dAi = np.linalg.inv(dA)  # 2 x 2 per feature: W(dp)^-1 = (dA^-1, -dA^-1 dt)
        dti = -np.einsum("nij,nj->ni", dAi, dp[:, 4:])
        t[idx] = np.einsum("nij,nj->ni", A[idx], dti) + t[idx]
        A[idx] = A[idx] @ dAi
        active[idx] = np.linalg.norm(dti, axis=-1) > tol
    Iw = sample(image, warped(A, t, X))
    return A, t, ncc(Iw, T)
