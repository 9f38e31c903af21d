"""Kalman filter kernels: prediction, EKF update, iterated EKF update (batched).

Textbook notation (Simon, *Optimal State Estimation*; FilterPy): state ``x (B, n)``,
covariance ``P (B, n, n)``, transition ``Phi``, process noise ``Q``, measurement
``y (B, m)``, model ``h(x)``, Jacobian ``H (B, m, n)``, measurement noise ``R`` given by
its diagonal ``(B, m)`` or ``(m,)``, innovation covariance ``S``, gain ``K``.
Every function returns new arrays; nothing is mutated. No explicit inverses: gains
come from ``np.linalg.solve`` on ``S``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import expm

Array = NDArray[np.float64]

# measure(x, rows) -> (h(x) (b, m), H(x) (b, m, n) or None when jac=False); ``rows``
# indexes the trials of the batch that ``x`` holds (the per-trial inputs follow them).
Measure = Callable[..., tuple[Array, Array | None]]


def symmetrize(P: Array) -> Array:
    """``(P + P^T) / 2``."""
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def transition_matrix(F: Array, dt: float, method: str = "taylor", order: int = 4) -> Array:
    """``Phi = expm(F dt)``, exactly (``"expm"``) or by its Taylor series to ``order``.

    The Taylor form ``sum_{j<=order} (F dt)^j / j!`` is evaluated by Horner's rule.
    """
    A = F * dt
    if method == "expm":
        return expm(A)
    n = F.shape[-1]
    eye = np.eye(n)
    Phi = eye + A / order
    for j in range(order - 1, 0, -1):
        Phi = eye + (A @ Phi) / j
    return Phi


def predict_covariance(P: Array, Phi: Array, Q: Array) -> Array:
    """``P- = Phi P Phi^T + Q`` with ``Q`` diagonal (``(n,)`` or ``(B, n)``), symmetrized."""
    P_pred = Phi @ P @ np.swapaxes(Phi, -1, -2)
    idx = np.arange(P.shape[-1])
    P_pred[..., idx, idx] += Q
    return symmetrize(P_pred)


def innovation_covariance(P: Array, H: Array, R: Array) -> Array:
    """``S = H P H^T + R`` with ``R`` diagonal ``(.., m)``."""
    S = H @ P @ np.swapaxes(H, -1, -2)
    idx = np.arange(S.shape[-1])
    S[..., idx, idx] += R
    return S


def gain(P: Array, H: Array, S: Array) -> Array:
    """``K = P H^T S^-1``, computed as ``solve(S, H P)^T`` (``S``, ``P`` symmetric)."""
    return np.swapaxes(np.linalg.solve(S, H @ P), -1, -2)


def joseph(P: Array, K: Array, H: Array, R: Array) -> Array:
    """Joseph form ``P+ = (I - K H) P (I - K H)^T + K R K^T`` (``R`` diagonal), symmetrized."""
    IKH = np.eye(P.shape[-1]) - K @ H
    KRK = (K * R[..., None, :]) @ np.swapaxes(K, -1, -2)
    return symmetrize(IKH @ P @ np.swapaxes(IKH, -1, -2) + KRK)


def mahalanobis2(v: Array, S: Array) -> Array:
    """``v^T S^-1 v`` per batch element (``v (.., m)``, ``S (.., m, m)``)."""
    return np.einsum("...i,...i->...", v, np.linalg.solve(S, v[..., None])[..., 0])


@dataclass(frozen=True)
class Update:
    """Result of a measurement update of a batch."""

    x: Array  # (B, n) posterior state
    P: Array  # (B, n, n) posterior covariance
    nu: Array  # (B, m) innovation at the prior, y - h(x-)
    S: Array  # (B, m, m) its covariance at the prior
    iterations: Array  # (B,) int, 1 for the EKF
    converged: Array  # (B,) bool, True for the EKF


def ekf_update(x: Array, P: Array, y: Array, measure: Measure, R: Array, rows: Array) -> Update:
    """EKF update: ``K = P H^T (H P H^T + R)^-1``, ``x+ = x + K (y - h(x))``, Joseph ``P+``."""
    hx, H = measure(x, rows, jac=True)
    S = innovation_covariance(P, H, R)
    K = gain(P, H, S)
    nu = y - hx
    x_new = x + np.einsum("...ij,...j->...i", K, nu)
    B = x.shape[0]
    return Update(x_new, joseph(P, K, H, R), nu, S, np.ones(B, int), np.ones(B, bool))


def map_cost(x: Array, x_prior: Array, P_prior: Array, y: Array, hx: Array, R: Array) -> Array:
    """MAP cost ``(x - x-)^T P-^-1 (x - x-) + (y - h(x))^T R^-1 (y - h(x))`` per trial."""
    e = x - x_prior
    r = y - hx
    return np.einsum("...i,...i->...", e, np.linalg.solve(P_prior, e[..., None])[..., 0]) + np.sum(r * r / R, axis=-1)


def step_size(dx: Array, P_prior: Array, stopping: str, H: Array | None = None, R: Array | None = None) -> Array:
    """Unit-free size of an IEKF increment ``dx`` for the stopping test.

    ``mahalanobis``: ``sqrt(dx^T (P-^-1 + H^T R^-1 H) dx)``, the increment in standard
    deviations of the (linearized) posterior, whose information matrix is
    ``P-^-1 + H^T R^-1 H``; computed without forming it.
    ``prior``: ``sqrt(dx^T P-^-1 dx)``; ``scaled``: ``max_i |dx_i| / sqrt(P-_ii)``;
    ``raw``: ``|dx|`` (the thesis's test, which mixes metres, rad/s and k).
    """
    if stopping in ("mahalanobis", "prior"):
        d2 = mahalanobis2(dx, P_prior)
        if stopping == "mahalanobis":
            Hdx = np.einsum("...ij,...j->...i", H, dx)
            d2 = d2 + np.sum(Hdx * Hdx / R, axis=-1)
        return np.sqrt(np.maximum(d2, 0.0))
    if stopping == "scaled":
        return np.max(np.abs(dx) / np.sqrt(np.diagonal(P_prior, axis1=-2, axis2=-1)), axis=-1)
    if stopping == "raw":
        return np.linalg.norm(dx, axis=-1)
    raise ValueError(f"unknown stopping test {stopping!r}")


def iekf_update(
    x_prior: Array,
    P_prior: Array,
    y: Array,
    measure: Measure,
    R: Array,
    rows: Array,
    tol: float = 0.01,
    max_iter: int = 10,
    step_control: str = "line_search",
    stopping: str = "mahalanobis",
    max_halvings: int = 10,
    renormalize: Callable[[Array], Array] | None = None,
) -> Update:
    """Iterated EKF update in Gauss-Newton form, with optional step control.

    From ``x^0 = x-``, the Gauss-Newton point of iterate ``x^j`` is

        x_GN = x- + K_j [y - h(x^j) - H_j (x- - x^j)],   K_j = P- H_j^T (H_j P- H_j^T + R)^-1

    which minimizes the linearized MAP cost
    ``J(x) = (x - x-)^T P-^-1 (x - x-) + (y - h(x))^T R^-1 (y - h(x))``. ``step_control``:

    - ``none``: ``x^{j+1} = x_GN`` (the standard IEKF; the thesis's algorithm 2 plus the
      ``H_j (x- - x^j)`` term it omits);
    - ``line_search``: ``x^{j+1} = x^j + a (x_GN - x^j)`` with ``a = 1, 1/2, 1/4, ...``
      the first that does not increase ``J``; if none within ``max_halvings`` halvings
      does, the trial stops at ``x^j`` (not converged);
    - ``levenberg_marquardt``: the step minimizes the linearized cost plus
      ``lam dx^T P-^-1 dx``, i.e. a Gauss-Newton step with prior covariance
      ``P-/(1+lam)``: ``dx = K_lam r - (I - K_lam H)(x^j - x-)/(1 + lam)``, accepted when
      ``J`` does not increase; ``lam`` (from 1e-3) is divided by 10 after an accepted
      step and multiplied by 10 after a rejected one.

    Each trial stops on its own (masking) once an accepted increment has
    ``step_size(...) < tol`` (converged) or after ``max_iter`` iterations. ``P+`` is the
    Joseph form with ``H_j, K_j`` of the iterate from which the final state was reached.
    ``nu, S`` are those at the prior (the EKF's innovation), for the NIS.
    """
    B = x_prior.shape[0]
    ren = renormalize if renormalize is not None else (lambda z: z)
    Rb = np.broadcast_to(R, y.shape)
    x = x_prior.copy()
    hx, H = measure(x, rows, jac=True)
    S = innovation_covariance(P_prior, H, Rb)
    K = gain(P_prior, H, S)
    nu0, S0 = y - hx, S
    H_fin, K_fin = H.copy(), K.copy()
    cost = map_cost(x, x_prior, P_prior, y, hx, Rb) if step_control != "none" else np.zeros(B)
    lam = np.full(B, 1e-3)
    iterations = np.zeros(B, int)
    converged = np.zeros(B, bool)
    active = np.arange(B)
    for it in range(max_iter):
        a = active
        xa, xpa, Pa, ya, Ra = x[a], x_prior[a], P_prior[a], y[a], Rb[a]
        r = ya - hx
        if step_control == "levenberg_marquardt":
            x_new, c_new, ok = _lm_step(xa, xpa, Pa, ya, Ra, r, H, lam[a], cost[a], measure, rows[a], ren)
            lam[a] = np.where(ok, lam[a] / 10.0, lam[a] * 10.0)
        else:
            x_gn = ren(xpa + np.einsum("...ij,...j->...i", K, r - np.einsum("...ij,...j->...i", H, xpa - xa)))
            if step_control == "none":
                x_new, c_new, ok = x_gn, cost[a], np.ones(a.size, bool)
            elif step_control == "line_search":
                x_new, c_new, ok = _line_search(xa, x_gn, xpa, Pa, ya, Ra, cost[a], measure, rows[a], ren, max_halvings)
            else:
                raise ValueError(f"unknown step_control {step_control!r}")
        iterations[a] += 1
        small = ok & (step_size(x_new - xa, Pa, stopping, H, Ra) < tol)
        H_fin[a[ok]] = H[ok]
        K_fin[a[ok]] = K[ok]
        x[a], cost[a] = x_new, c_new
        converged[a[small]] = True
        done = small | (~ok if step_control == "line_search" else False)
        active = a[~done]
        if active.size == 0 or it == max_iter - 1:
            break
        hx, H = measure(x[active], rows[active], jac=True)
        S = innovation_covariance(P_prior[active], H, Rb[active])
        K = gain(P_prior[active], H, S)
    P_post = joseph(P_prior, K_fin, H_fin, Rb)
    return Update(x, P_post, nu0, S0, iterations, converged)


def _line_search(xa, x_gn, xpa, Pa, ya, Ra, cost_a, measure, rows, ren, max_halvings):
    """Backtracking from ``xa`` toward ``x_gn`` until the MAP cost does not increase."""
    d = x_gn - xa
    alpha = np.ones(xa.shape[0])
    x_new, cost_new = xa.copy(), cost_a.copy()
    accepted = np.zeros(xa.shape[0], bool)
    todo = np.arange(xa.shape[0])
    for _ in range(max_halvings + 1):
        xt = ren(xa[todo] + alpha[todo, None] * d[todo])
        ht, _ = measure(xt, rows[todo], jac=False)
        ct = map_cost(xt, xpa[todo], Pa[todo], ya[todo], ht, Ra[todo])
        ok = np.isfinite(ct) & (ct <= cost_a[todo])
        x_new[todo[ok]], cost_new[todo[ok]], accepted[todo[ok]] = xt[ok], ct[ok], True
        todo = todo[~ok]
        if todo.size == 0:
            break
        alpha[todo] *= 0.5
    return x_new, cost_new, accepted


def _lm_step(xa, xpa, Pa, ya, Ra, r, H, lam, cost_a, measure, rows, ren):
    """One Levenberg-Marquardt trial step with prior-scaled damping (see ``iekf_update``)."""
    s = 1.0 + lam
    P_l = Pa / s[:, None, None]
    K_l = gain(P_l, H, innovation_covariance(P_l, H, Ra))
    e = xa - xpa
    dx = np.einsum("...ij,...j->...i", K_l, r) - (e - np.einsum("...ij,...jk,...k->...i", K_l, H, e)) / s[:, None]
    xt = ren(xa + dx)
    ht, _ = measure(xt, rows, jac=False)
    c_new = map_cost(xt, xpa, Pa, ya, ht, Ra)
    ok = np.isfinite(c_new) & (c_new <= cost_a)
    return np.where(ok[:, None], xt, xa), np.where(ok, c_new, cost_a), ok
