"""Unscented transform and Kalman filter kernels (scaled sigma points), batched over trials.

Sigma points of van der Merwe (as FilterPy's ``MerweScaledSigmaPoints``): with
``lam = alpha^2 (n + kappa) - n`` and ``P = L L^T`` (Cholesky),

    chi_0 = x,  chi_i = x [+] sqrt(n + lam) L[:, i],  chi_{n+i} = x [+] (-sqrt(n + lam) L[:, i])

weights ``Wm_0 = lam / (n + lam)``, ``Wc_0 = Wm_0 + 1 - alpha^2 + beta``,
``Wm_i = Wc_i = 1 / (2 (n + lam))``.

The state may live on a manifold: ``chart(x, d)`` (``x [+] d``) and ``local(x_ref, x)`` (its
inverse) map between states and their ``n``-dimensional increments; by default both are
additive. Sigma points of ``B`` trials are arrays ``(B, 2n+1, .)``; ``f`` and ``h`` are
called on them flattened to ``(B (2n+1), .)`` with the trial index of each point.

- ``predict``: ``chi_i' = f(chi_i)``; the mean increment ``d = sum Wm_i local(chi_0', chi_i')``
  relative to the propagated centre point, ``x- = chi_0' [+] d`` and
  ``P- = sum Wc_i (local(chi_0', chi_i') - d)(...)^T + Q`` (Crassidis & Markley's USQUE for
  a multiplicative attitude; the ordinary unscented transform when additive);
- ``update``: new sigma points of ``(x-, P-)``, ``y_i = h(chi_i)``, ``y_bar = sum Wm_i y_i``,
  ``S = sum Wc_i (y_i - y_bar)(...)^T + R``, ``C = sum Wc_i d_i (y_i - y_bar)^T``,
  ``K = C S^-1`` (a solve), ``x+ = x- [+] K (y - y_bar)``, ``P+ = P- - K S K^T``; NIS
  ``nu^T S^-1 nu`` with ``nu = y - y_bar``.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def additive_chart(x: Array, d: Array) -> Array:
    return x + d


def additive_local(x_ref: Array, x: Array) -> Array:
    return x - x_ref


def weights(n: int, alpha: float, beta: float, kappa: float) -> tuple[Array, Array, float]:
    """``(Wm, Wc, lam)`` of the scaled sigma points for dimension ``n``."""
    lam = alpha**2 * (n + kappa) - n
    Wm = np.full(2 * n + 1, 0.5 / (n + lam))
    Wc = Wm.copy()
    Wm[0] = lam / (n + lam)
    Wc[0] = Wm[0] + 1.0 - alpha**2 + beta
    return Wm, Wc, lam


def sigma_offsets(P: Array, lam: float) -> Array:
    """Increments ``(B, 2n+1, n)``: 0, then ``+-`` the columns of ``sqrt(n + lam) chol(P)``."""
    n = P.shape[-1]
    L = np.sqrt(n + lam) * np.linalg.cholesky(P)
    cols = np.swapaxes(L, -1, -2)  # row i = column i of L
    return np.concatenate([np.zeros(P.shape[:-2] + (1, n)), cols, -cols], axis=-2)


def sigma_points(x: Array, P: Array, lam: float, chart: Callable = additive_chart) -> Array:
    """``chi (B, 2n+1, len(x))``."""
    d = sigma_offsets(P, lam)
    return chart(np.broadcast_to(x[..., None, :], d.shape[:-1] + x.shape[-1:]), d)


def _flat(a: Array) -> Array:
    return a.reshape((-1,) + a.shape[2:])


def weighted_outer(W: Array, a: Array, b: Array) -> Array:
    """``sum_k W_k a_k b_k^T`` (``(B, n, m)`` from ``a (B, K, n)``, ``b (B, K, m)``) as ``(a W)^T b``: one batched
    BLAS product per trial (a three-operand ``einsum`` loops in C without BLAS, ~20x slower here)."""
    return np.swapaxes(a * W[:, None], -1, -2) @ b


def predict(x: Array, P: Array, f: Callable, Q: Array, alpha: float, beta: float, kappa: float,
            chart: Callable = additive_chart, local: Callable = additive_local) -> tuple[Array, Array]:  # fmt: skip
    """``(x-, P-)``; ``f(states (M, .), trial_of_point (M,))`` propagates flattened points."""
    B, n = P.shape[0], P.shape[-1]
    Wm, Wc, lam = weights(n, alpha, beta, kappa)
    chi = sigma_points(x, P, lam, chart)
    idx = np.repeat(np.arange(B), 2 * n + 1)
    chi_f = f(_flat(chi), idx).reshape(chi.shape)
    ref = chi_f[:, 0]
    dev = local(np.broadcast_to(ref[:, None], chi_f.shape), chi_f)  # (B, 2n+1, n)
    d = np.einsum("k,bki->bi", Wm, dev)
    e = dev - d[:, None]
    P_pred = weighted_outer(Wc, e, e) + Q
    return chart(ref, d), 0.5 * (P_pred + np.swapaxes(P_pred, -1, -2))


def update(x: Array, P: Array, y: Array, h: Callable, R: Array, alpha: float, beta: float, kappa: float,
           chart: Callable = additive_chart) -> tuple[Array, Array, Array, Array]:  # fmt: skip
    """``(x+, P+, nu, nis)``; ``h(states (M, .), trial_of_point (M,))``; ``R`` diagonal ``(.., m)``."""
    B, n = P.shape[0], P.shape[-1]
    Wm, Wc, lam = weights(n, alpha, beta, kappa)
    d = sigma_offsets(P, lam)
    chi = chart(np.broadcast_to(x[:, None], d.shape[:-1] + x.shape[-1:]), d)
    idx = np.repeat(np.arange(B), 2 * n + 1)
    Y = h(_flat(chi), idx).reshape(B, 2 * n + 1, -1)
    y_bar = np.einsum("k,bkm->bm", Wm, Y)
    dy = Y - y_bar[:, None]
    S = weighted_outer(Wc, dy, dy)
    m = S.shape[-1]
    S[..., np.arange(m), np.arange(m)] += np.broadcast_to(R, (B, m))
    C = weighted_outer(Wc, d, dy)  # (B, n, m); the centre offset is 0
    nu = y - y_bar
    Z = np.linalg.solve(S, np.concatenate([np.swapaxes(C, -1, -2), nu[..., None]], axis=-1))
    K = np.swapaxes(Z[..., :-1], -1, -2)
    nis = np.einsum("bi,bi->b", nu, Z[..., -1])
    P_new = P - K @ S @ np.swapaxes(K, -1, -2)
    x_new = chart(x, np.einsum("bij,bj->bi", K, nu))
    return x_new, 0.5 * (P_new + np.swapaxes(P_new, -1, -2)), nu, nis
