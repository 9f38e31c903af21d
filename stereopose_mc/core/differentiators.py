"""Causal differentiation of sampled noisy signals (thesis appendix B).

Three estimators of the derivative of a signal ``w(t)`` sampled at uniform spacing
``dt``, each using only the past (causal), for the inertia pseudo-measurement's angular
acceleration ``alpha = d omega / dt`` (docs/model.md, docs/angular-acceleration.md):

- **Savitzky-Golay** (local polynomial least squares, appendix B.1): fit a polynomial
  of degree ``p`` to the newest ``W`` samples and differentiate it at the newest one;
- **Tikhonov** (appendix B.2): the derivative samples ``a`` minimize
  ``||A a dt - (w - w_0)||^2 + lam ||D a dt||^2`` over the window (``A`` the
  trapezoidal integration operator, ``D`` a difference operator), read at the newest
  sample;
- **Han's tracking differentiator** (appendix B.3) in its discrete, time-optimal form
  with ``fhan``: a nonlinear second-order system whose first state tracks the signal
  and whose second state is the derivative estimate. It is stateful: the state is an
  explicit array passed in and returned.

The first two are linear: the derivative at the newest sample is ``c . w`` with a
weight vector ``c (W,)`` fixed by ``(W, dt, ...)``; for independent samples of
variances ``s_j`` its variance is ``sum_j c_j^2 s_j``. The tracking differentiator is
linear in its small-signal ("linear") zone, where its error covariance follows a
Lyapunov recursion carried alongside its state (``td_covariance_step``).

Shapes: windows ``w (..., W, d)`` (window axis ``-2``, components ``-1``), any leading
batch axes; series ``x (..., T, d)``; tracking-differentiator state ``(..., 2, d)``
(``[..., 0, :]`` tracks the signal, ``[..., 1, :]`` its derivative). Outputs keep the
input's rank. Pure functions: nothing is mutated.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


# ---------------------------------------------------------------------------
# linear estimators: weights, application, variance


def savgol_weights(window: int, polyorder: int, dt: float) -> Array:
    """Weights ``c (W,)`` of the causal Savitzky-Golay first derivative at the newest sample.

    With ``tau_j = (j - (W-1)) dt`` (``j = 0..W-1``, newest last), the least-squares
    polynomial ``f(tau) = sum_{m<=p} b_m tau^m`` of the window gives
    ``f'(0) = b_1 = e_1^T (V^T V)^-1 V^T w = c . w`` (``V_jm = tau_j^m``). It is exact for
    polynomials of degree ``<= p`` (scipy ``savgol_coeffs(W, p, deriv=1, delta=dt,
    pos=W-1, use='dot')``).
    """
    if not 0 < polyorder < window:
        raise ValueError(f"need 0 < polyorder ({polyorder}) < window ({window})")
    if not dt > 0:
        raise ValueError(f"dt must be > 0 (got {dt})")
    from scipy.signal import savgol_coeffs  # scipy.signal takes ~0.5 s to import: only when used

    return np.asarray(savgol_coeffs(window, polyorder, deriv=1, delta=dt, pos=window - 1, use="dot"), dtype=float)


def integration_operator(window: int) -> Array:
    """Trapezoidal cumulative integral ``A (W-1, W)`` in units of ``dt``.

    Row ``j-1`` (``j = 1..W-1``): ``int_0^{t_j} a dt / dt ~ a_0/2 + a_1 + ... + a_{j-1} + a_j/2``.
    Exact for ``a`` linear in ``t``.
    """
    A = np.tril(np.ones((window - 1, window)), k=1)
    A[:, 0] = 0.5
    A[np.arange(window - 1), np.arange(1, window)] = 0.5
    return A


def difference_operator(window: int, order: int) -> Array:
    """Forward difference ``D`` of ``order`` 1 (``(W-1, W)``, rows ``[-1, 1]``) or 2 (``(W-2, W)``, ``[1, -2, 1]``)."""
    if order not in (1, 2):
        raise ValueError(f"difference order must be 1 or 2 (got {order})")
    return np.diff(np.eye(window), n=order, axis=0)


def tikhonov_weights(window: int, lam: float, dt: float, order: int = 2) -> Array:
    """Weights ``c (W,)`` of the Tikhonov-regularized derivative at the newest sample.

    With ``y_j = w_j - w_0`` (``j = 1..W-1``, i.e. ``y = M w``, ``M = [-1 | I]``) and
    ``s = a dt`` (the derivative samples in units of ``w`` per step), ``s`` minimizes

        ||A s - y||^2 + lam ||D s||^2,    (A^T A + lam D^T D) s = A^T y     (thesis B.5-B.6)

    with ``A = integration_operator``, ``D = difference_operator(order)``; ``lam`` is
    dimensionless (the cost is written per step). For ``lam > 0`` the normal matrix
    ``N`` is positive definite (``A`` has full row rank and its null vector
    ``(+1, -1, +1, ...)`` is not in the null space of ``D``). The derivative at the
    newest sample is ``a_{W-1} = e^T N^-1 A^T M w / dt = c . w`` with
    ``c = M^T A z / dt``, ``N z = e`` (one solve, no inverse). Exact for polynomials of
    degree ``<= order`` for any ``lam`` (their derivative satisfies ``A s = y`` exactly
    and ``D s = 0``).
    """
    if window < order + 2:
        raise ValueError(f"window ({window}) must be at least order + 2 = {order + 2}")
    if not lam > 0:
        raise ValueError(f"tikhonov lambda must be > 0 (got {lam})")
    if not dt > 0:
        raise ValueError(f"dt must be > 0 (got {dt})")
    A = integration_operator(window)
    D = difference_operator(window, order)
    N = A.T @ A + lam * (D.T @ D)
    e = np.zeros(window)
    e[-1] = 1.0
    z = np.linalg.solve(N, e)
    Az = A @ z
    c = np.concatenate([[-Az.sum()], Az])  # M^T A z
    return c / dt


def tikhonov_solve(w: Array, lam: float, dt: float, order: int = 2) -> Array:
    """All derivative samples ``a (..., W, d)`` of the Tikhonov problem over windows ``w (..., W, d)``."""
    W = w.shape[-2]
    A = integration_operator(W)
    D = difference_operator(W, order)
    N = A.T @ A + lam * (D.T @ D)
    y = w[..., 1:, :] - w[..., :1, :]
    rhs = np.einsum("jk,...jd->...kd", A, y)
    s = np.linalg.solve(np.broadcast_to(N, rhs.shape[:-2] + (W, W)), rhs)
    return s / dt


def apply_weights(c: Array, w: Array) -> Array:
    """``sum_j c_j w[..., j, :]``: the linear estimate ``(..., d)`` from windows ``w (..., W, d)``."""
    if w.shape[-2] != c.shape[-1]:
        raise ValueError(f"window length {w.shape[-2]} does not match {c.shape[-1]} weights")
    return np.einsum("j,...jd->...d", c, w)


def weights_variance(c: Array, var: Array) -> Array:
    """``sum_j c_j^2 var[..., j, :]``: variance of ``c . w`` for independent samples of variances ``var (..., W, d)``.

    The samples' covariances are neglected (docs/angular-acceleration.md says when that matters).
    """
    return apply_weights(c * c, var)


def causal_series(c: Array, x: Array) -> Array:
    """The linear estimate at every sample of a series ``x (..., T, d)`` from the ``W`` samples ending there.

    Entry ``t`` uses ``x[..., t-W+1 : t+1, :]`` only (causal); the first ``W-1`` entries are NaN.
    """
    W = c.shape[-1]
    T = x.shape[-2]
    out = np.full(x.shape, np.nan)
    if T >= W:
        win = np.lib.stride_tricks.sliding_window_view(x, W, axis=-2)  # (..., T-W+1, d, W)
        out[..., W - 1 :, :] = np.einsum("j,...dj->...d", c, win)
    return out


def truncation_bound(c: Array, dt: float, degree: int, deriv_bound: float) -> float:
    """Bound on the bias of a linear estimator exact for polynomials of degree ``<= degree``.

    With the Taylor expansion about the newest sample, the degree-``p`` part is
    differentiated exactly and the remainder obeys ``|R(tau)| <= M |tau|^{p+1} / (p+1)!``
    with ``M >= sup |w^{(p+1)}|`` (``deriv_bound``), so
    ``|c . w - w'(t_newest)| <= M / (p+1)! sum_j |c_j| |tau_j|^{p+1}``, ``tau_j = (j - (W-1)) dt``.
    """
    W = c.shape[-1]
    tau = (np.arange(W) - (W - 1)) * dt
    p1 = degree + 1
    return float(deriv_bound * np.sum(np.abs(c) * np.abs(tau) ** p1) / np.prod(np.arange(1, p1 + 1)))


# ---------------------------------------------------------------------------
# Han's tracking differentiator


def _fsg(x: Array, d: float | Array) -> Array:
    """``(sign(x + d) - sign(x - d)) / 2``: 1 inside ``|x| < d``, 0 outside (1/2 on the edge)."""
    return 0.5 * (np.sign(x + d) - np.sign(x - d))


def fhan(x1: Array, x2: Array, r: float, h0: float) -> Array:
    """Han's time-optimal synthesis function ``fhan(x1, x2, r, h0)`` (Han 2009, IEEE TIE 56(3)).

        d  = r h0^2,  a0 = h0 x2,  y = x1 + a0,  a1 = sqrt(d (d + 8|y|)),
        a2 = a0 + sign(y) (a1 - d) / 2,
        a  = (a0 + y) fsg(y, d) + a2 (1 - fsg(y, d)),
        fhan = -r (a / d) fsg(a, d) - r sign(a) (1 - fsg(a, d)).

    ``|fhan| <= r``. In its linear zone (``|y| < d`` and ``|a| < d``) it is
    ``-x1 / h0^2 - 2 x2 / h0`` (independent of ``r``).
    """
    d = r * h0 * h0
    a0 = h0 * x2
    y = x1 + a0
    a1 = np.sqrt(d * (d + 8.0 * np.abs(y)))
    a2 = a0 + np.sign(y) * (a1 - d) / 2.0
    sy = _fsg(y, d)
    a = (a0 + y) * sy + a2 * (1.0 - sy)
    sa = _fsg(a, d)
    return -r * (a / d) * sa - r * np.sign(a) * (1.0 - sa)


def td_init(v: Array) -> Array:
    """Initial state ``(..., 2, d)`` from the first sample ``v (..., d)``: tracking ``v``, derivative 0."""
    return np.stack([v, np.zeros_like(v)], axis=-2)


def td_step(state: Array, v: Array, dt: float, r: float, h0: float) -> tuple[Array, Array]:
    """One step of the discrete tracking differentiator with the new sample ``v (..., d)``.

        x1+ = x1 + dt x2
        x2+ = x2 + dt fhan(x1 - v, x2, r, h0)

    Returns ``(state+, x2+)``: the new state ``(..., 2, d)`` and the derivative estimate
    ``(..., d)`` after the sample (in the linear zone it lags a changing derivative by ``2 h0 - 1.5 dt``).
    ``r`` bounds ``|d x2/dt|`` (units of ``v`` per s^2); ``h0`` (s) is the filtering time.
    """
    x1 = state[..., 0, :]
    x2 = state[..., 1, :]
    x1n = x1 + dt * x2
    x2n = x2 + dt * fhan(x1 - v, x2, r, h0)
    return np.stack([x1n, x2n], axis=-2), x2n


def td_series(x: Array, dt: float, r: float, h0: float, state: Array | None = None) -> tuple[Array, Array]:
    """Run the tracking differentiator over a series ``x (..., T, d)``.

    Returns the derivative estimates ``(..., T, d)`` (entry ``t`` after sample ``t``) and
    the final state. Without ``state`` it starts from ``td_init(x[..., 0, :])``.
    """
    s = td_init(x[..., 0, :]) if state is None else state
    out = np.empty(x.shape)
    for t in range(x.shape[-2]):
        s, out[..., t, :] = td_step(s, x[..., t, :], dt, r, h0)
    return out, s


def td_linear_system(dt: float, h0: float) -> tuple[Array, Array]:
    """``(Phi (2, 2), b (2,))`` of the tracking differentiator in its linear zone: ``s+ = Phi s + b v``.

    From ``fhan = -(x1 - v)/h0^2 - 2 x2/h0``:
    ``Phi = [[1, dt], [-dt/h0^2, 1 - 2 dt/h0]]``, ``b = [0, dt/h0^2]``; a double pole at
    ``1 - dt/h0`` (critically damped), stable for ``0 < dt/h0 < 2``.
    """
    Phi = np.array([[1.0, dt], [-dt / h0**2, 1.0 - 2.0 * dt / h0]])
    b = np.array([0.0, dt / h0**2])
    return Phi, b


def td_impulse_response(dt: float, h0: float, n: int) -> Array:
    """``g (n,)``: the derivative output's response ``x2+`` to a unit input ``n - 1 .. 0`` samples ago.

    ``g_m = [Phi^m b]_2`` (``m = 0`` the newest sample), so in the linear zone
    ``x2+_k = sum_m g_m v_{k-m}`` plus the decaying initial-state term.
    """
    Phi, b = td_linear_system(dt, h0)
    g = np.empty(n)
    s = b.copy()
    for m in range(n):
        g[m] = s[1]
        s = Phi @ s
    return g


def td_noise_gain(dt: float, h0: float) -> float:
    """Stationary ``G = sum_{m>=0} g_m^2`` (1/s^2): ``Var(x2+) = G sigma^2`` for white input of variance ``sigma^2``.

    ``sum_m Phi^m b b^T Phi^mT = S`` solves the discrete Lyapunov equation
    ``S = Phi S Phi^T + b b^T`` (the stationary covariance of the state after the update
    per unit input variance), so ``G = S_22``.
    """
    Phi, b = td_linear_system(dt, h0)
    if not 0.0 < dt / h0 < 2.0:
        raise ValueError(f"tracking differentiator unstable in its linear zone: dt/h0 = {dt / h0} not in (0, 2)")
    from scipy.linalg import solve_discrete_lyapunov  # here, not at import: scipy.linalg costs ~0.1 s

    S = solve_discrete_lyapunov(Phi, np.outer(b, b))
    return float(S[1, 1])


def td_covariance_init(var0: Array) -> Array:
    """Linear-zone error covariance ``(..., 3, d)`` (``[S11, S12, S22]``) of ``td_init``: ``diag(var0, 0)``.

    ``td_init`` copies the first sample, so the tracking state's error is that sample's
    error (variance ``var0 (..., d)``); the derivative state starts at 0 (its bias
    ``-w'(t_0)`` is not a noise term and is left out).
    """
    z = np.zeros_like(var0)
    return np.stack([var0, z, z], axis=-2)


def td_covariance_step(S: Array, var: Array, dt: float, h0: float) -> Array:
    """``S+ = Phi S Phi^T + b b^T var``: the linear-zone error covariance after a sample of variance ``var (..., d)``.

    ``S (..., 3, d)`` holds ``[S11, S12, S22]`` of the 2x2 covariance of the state's
    error per component (independent input errors). With ``Phi = [[1, dt], [p, q]]``,
    ``p = -dt/h0^2``, ``q = 1 - 2 dt/h0``, ``b = [0, dt/h0^2]`` (``td_linear_system``):

        S11+ = S11 + 2 dt S12 + dt^2 S22
        S12+ = p S11 + (q + dt p) S12 + dt q S22
        S22+ = p^2 S11 + 2 p q S12 + q^2 S22 + (dt/h0^2)^2 var

    ``S22+`` is the variance of the derivative estimate ``x2+``. Outside the linear zone
    (saturated ``fhan``) the noise response is smaller (``|d x2/dt| <= r``), so there it
    over-estimates the noise part (it does not describe a slewing transient).
    """
    p = -dt / h0**2
    q = 1.0 - 2.0 * dt / h0
    beta = dt / h0**2
    s11, s12, s22 = S[..., 0, :], S[..., 1, :], S[..., 2, :]
    n11 = s11 + 2.0 * dt * s12 + dt * dt * s22
    n12 = p * s11 + (q + dt * p) * s12 + dt * q * s22
    n22 = p * p * s11 + 2.0 * p * q * s12 + q * q * s22 + beta * beta * var
    return np.stack([n11, n12, n22], axis=-2)
