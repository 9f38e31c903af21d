"""Generic batched Kalman algebra: prediction, EKF update, iterated EKF update (``filters/`` binds it
to the relative-navigation problem).

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
        from scipy.linalg import expm  # here, not at import: scipy.linalg costs ~0.1 s, Taylor is the default

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
    nis: Array  # (B,) normalized innovation squared nu^T S^-1 nu, S = H P- H^T + R at the prior
    iterations: Array  # (B,) int, 1 for the EKF
    converged: Array  # (B,) bool, True for the EKF


def ekf_update(x: Array, P: Array, y: Array, measure: Measure, R: Array, rows: Array) -> Update:
    """EKF update: ``K = P H^T (H P H^T + R)^-1``, ``x+ = x + K (y - h(x))``, Joseph ``P+``."""
    hx, H = measure(x, rows, jac=True)
    R = np.broadcast_to(R, y.shape)
    S = innovation_covariance(P, H, R)
    nu = y - hx
    # one solve for the gain and the NIS: S^-1 [H P | nu]
    HP = H @ P
    Z = np.linalg.solve(S, np.concatenate([HP, nu[..., None]], axis=-1))
    K = np.swapaxes(Z[..., :-1], -1, -2)
    nis = np.einsum("...i,...i->...", nu, Z[..., -1])
    x_new = x + np.einsum("...ij,...j->...i", K, nu)
    B = x.shape[0]
    return Update(x_new, joseph(P, K, H, R), nu, nis, np.ones(B, int), np.ones(B, bool))


def map_cost(x: Array, x_prior: Array, P_prior: Array, y: Array, hx: Array, R: Array) -> Array:
    """MAP cost ``(x - x-)^T P-^-1 (x - x-) + (y - h(x))^T R^-1 (y - h(x))`` per trial."""
    e = x - x_prior
    r = y - hx
    return mahalanobis2(e, P_prior) + np.sum(r * r / R, axis=-1)


STOPPING_TESTS = ("mahalanobis", "prior", "scaled", "raw")
STEP_CONTROLS = ("line_search", "levenberg_marquardt", "none")


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
) -> Update:
    """Iterated EKF update in Gauss-Newton form, with optional step control.

    The IEKF minimizes the MAP cost
    ``J(x) = (x - x-)^T P-^-1 (x - x-) + (y - h(x))^T R^-1 (y - h(x))``. From
    ``x^0 = x-``, the Gauss-Newton point of the iterate ``x^j`` is

        x_GN = x- + K_j [y - h(x^j) - H_j (x- - x^j)],   K_j = P- H_j^T (H_j P- H_j^T + R)^-1

    It is computed in whitened coordinates ``x = x- + L z`` (``P- = L L^T``, Cholesky,
    once per update) with ``Hw = R^-1/2 H L`` and ``rw = R^-1/2 (y - h(x^j))``, where the
    cost is ``|z|^2 + |rw(z)|^2`` and the Gauss-Newton point solves the n x n system
    ``(I + Hw^T Hw) z_GN = Hw^T (rw + Hw z_j)`` (the same point as the gain form above,
    by the push-through identity, for an n x n instead of an m x m solve).

    ``step_control``:

    - ``none``: ``z^{j+1} = z_GN`` (the standard IEKF; the thesis's algorithm 2 plus the
      ``H_j (x- - x^j)`` term it omits);
    - ``line_search``: ``z^{j+1} = z^j + a (z_GN - z^j)`` with ``a = 1, 1/2, 1/4, ...``
      the first that does not increase ``J``; if none within ``max_halvings`` halvings
      does, the trial stops at ``x^j`` (not converged);
    - ``levenberg_marquardt``: ``z^{j+1}`` minimizes the linearized cost plus
      ``lam |z - z^j|^2 = lam (x - x^j)^T P-^-1 (x - x^j)``:
      ``((1 + lam) I + Hw^T Hw) z = Hw^T (rw + Hw z_j) + lam z_j``, accepted when ``J`` does
      not increase; ``lam`` (from 1e-3) is divided by 10 after an accepted step and
      multiplied by 10 after a rejected one.

    Each trial stops on its own (masking) once an accepted increment ``dx = L dz`` has
    size ``< tol`` (converged) or after ``max_iter`` iterations, the size being
    (``stopping``) ``mahalanobis``: ``sqrt(dx^T (P-^-1 + H^T R^-1 H) dx) = |[dz, Hw dz]|``,
    the increment in standard deviations of the linearized posterior; ``prior``:
    ``sqrt(dx^T P-^-1 dx) = |dz|``; ``scaled``: ``max_i |dx_i| / sqrt(P-_ii)``; ``raw``:
    ``|dx|`` (the thesis's test, which mixes metres, rad/s and k).

    ``P+`` is the Joseph form with ``H_j`` and ``K_j = L (I + Hw^T Hw)^-1 Hw^T R^-1/2`` of
    the iterate from which the final state was reached. ``nu, nis`` are those at the
    prior (the EKF's innovation). Iterates are not renormalized (``h`` of this model does
    not depend on the quaternion's norm); the caller renormalizes the final state.
    """
    if step_control not in STEP_CONTROLS:
        raise ValueError(f"unknown step_control {step_control!r}")
    if stopping not in STOPPING_TESTS:
        raise ValueError(f"unknown stopping test {stopping!r}")
    B, n = x_prior.shape
    Rb = np.broadcast_to(R, y.shape)
    rw_scale = 1.0 / np.sqrt(Rb)  # (B, m)
    L = np.linalg.cholesky(P_prior)
    eye = np.eye(n)

    def whiten(H, hx, a):
        Hw = (H @ L[a]) * rw_scale[a][..., None]
        rw = (y[a] - hx) * rw_scale[a]
        return Hw, rw, eye + np.swapaxes(Hw, -1, -2) @ Hw

    def to_x(z, a):
        return x_prior[a] + np.einsum("...ij,...j->...i", L[a], z)

    hx, H = measure(x_prior, rows, jac=True)
    Hw, rw, A = whiten(H, hx, np.arange(B))
    nu0 = y - hx
    # NIS by Woodbury: nu^T S^-1 nu = |rw|^2 - g^T A^-1 g, g = Hw^T rw
    g0 = np.einsum("...ji,...j->...i", Hw, rw)
    nis0 = np.sum(rw * rw, -1) - np.einsum("...i,...i->...", g0, np.linalg.solve(A, g0[..., None])[..., 0])
    z = np.zeros((B, n))
    cost = np.sum(rw * rw, axis=-1)  # J at z = 0
    H_fin, Hw_fin, A_fin = H.copy(), Hw.copy(), A.copy()
    lam = np.full(B, 1e-3)
    iterations = np.zeros(B, int)
    converged = np.zeros(B, bool)
    active = np.arange(B)
    for it in range(max_iter):
        a = active
        za = z[a]
        rhs = np.einsum("...ji,...j->...i", Hw, rw + np.einsum("...ij,...j->...i", Hw, za))
        if step_control == "levenberg_marquardt":
            z_try = np.linalg.solve(A + lam[a][:, None, None] * eye, (rhs + lam[a][:, None] * za)[..., None])[..., 0]
            z_new, c_new, ok = _accept(z_try, za, cost[a], measure, rows[a], to_x, y, rw_scale, a)
            lam[a] = np.where(ok, lam[a] / 10.0, lam[a] * 10.0)
        else:
            z_gn = np.linalg.solve(A, rhs[..., None])[..., 0]
            if step_control == "none":
                z_new, c_new, ok = z_gn, cost[a], np.ones(a.size, bool)
            else:
                z_new, c_new, ok = _line_search(z_gn, za, cost[a], measure, rows[a], to_x, y, rw_scale, a,
                                                max_halvings)  # fmt: skip
        iterations[a] += 1
        small = ok & (_increment_size(z_new - za, Hw, L[a], P_prior[a], stopping) < tol)
        H_fin[a[ok]], Hw_fin[a[ok]], A_fin[a[ok]] = H[ok], Hw[ok], A[ok]
        z[a], cost[a] = z_new, c_new
        converged[a[small]] = True
        done = small | (~ok if step_control == "line_search" else False)
        active = a[~done]
        if active.size == 0 or it == max_iter - 1:
            break
        hx, H = measure(to_x(z[active], active), rows[active], jac=True)
        Hw, rw, A = whiten(H, hx, active)
    x = to_x(z, np.arange(B))
    K = L @ np.linalg.solve(A_fin, np.swapaxes(Hw_fin, -1, -2)) * rw_scale[:, None, :]
    return Update(x, joseph(P_prior, K, H_fin, Rb), nu0, nis0, iterations, converged)


def _increment_size(dz: Array, Hw: Array, L: Array, P_prior: Array, stopping: str) -> Array:
    """Unit-free size of the increment ``dx = L dz`` (see ``iekf_update``)."""
    if stopping == "mahalanobis":
        Hdz = np.einsum("...ij,...j->...i", Hw, dz)
        return np.sqrt(np.sum(dz * dz, -1) + np.sum(Hdz * Hdz, -1))
    if stopping == "prior":
        return np.linalg.norm(dz, axis=-1)
    dx = np.einsum("...ij,...j->...i", L, dz)
    if stopping == "scaled":
        return np.max(np.abs(dx) / np.sqrt(np.diagonal(P_prior, axis1=-2, axis2=-1)), axis=-1)
    return np.linalg.norm(dx, axis=-1)


def _cost(z, measure, rows, to_x, y, rw_scale, a):
    """``J = |z|^2 + |R^-1/2 (y - h(x- + L z))|^2`` for the trials ``a``."""
    hx, _ = measure(to_x(z, a), rows, jac=False)
    r = (y[a] - hx) * rw_scale[a]
    return np.sum(z * z, -1) + np.sum(r * r, -1)


def _accept(z_try, za, cost_a, measure, rows, to_x, y, rw_scale, a):
    """Keep ``z_try`` where it does not increase the cost, else stay at ``za``."""
    c = _cost(z_try, measure, rows, to_x, y, rw_scale, a)
    ok = np.isfinite(c) & (c <= cost_a)
    return np.where(ok[:, None], z_try, za), np.where(ok, c, cost_a), ok


def _line_search(z_gn, za, cost_a, measure, rows, to_x, y, rw_scale, a, max_halvings):
    """Backtracking from ``za`` toward ``z_gn`` until the MAP cost does not increase."""
    d = z_gn - za
    alpha = np.ones(za.shape[0])
    z_new, cost_new = za.copy(), cost_a.copy()
    accepted = np.zeros(za.shape[0], bool)
    todo = np.arange(za.shape[0])
    for _ in range(max_halvings + 1):
        zt = za[todo] + alpha[todo, None] * d[todo]
        ct = _cost(zt, measure, rows[todo], to_x, y, rw_scale, a[todo])
        ok = np.isfinite(ct) & (ct <= cost_a[todo])
        z_new[todo[ok]], cost_new[todo[ok]], accepted[todo[ok]] = zt[ok], ct[ok], True
        todo = todo[~ok]
        if todo.size == 0:
            break
        alpha[todo] *= 0.5
    return z_new, cost_new, accepted
