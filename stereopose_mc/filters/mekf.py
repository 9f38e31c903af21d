"""Error-state filters of the relative-navigation problem, batched over trials.

The estimate keeps the full state ``x (B, n)`` with its unit quaternion; the covariance
is that of an error state ``e (n - 1)`` in one of two charts (``FilterSetup.error_state``,
docs/filters.md "Error state"):

- ``attitude`` (the multiplicative EKF): ``core.errorstate``, the attitude as a 3-vector
  ``a`` in ``L`` (``q = dq(a) (x) q_hat``), additive elsewhere;
- ``aligned`` (the default of the IEKF and the MEKF): ``core.aligned``, the points'
  centroid in ``L``, a body-frame rotation and the points in the rotated body frame, in
  which the centre-of-mass gauge and the body-frame rotation are straight lines.

Either way the covariance has no quaternion-norm direction, and:

- **Prediction**: ``x- = RK4(f, x+)`` as the EKF; the error-state transition is the full
  one seen through the chart, ``Phi_e = T(x-) Phi S(x+)`` (``S = d x / d e`` at ``e = 0``,
  ``T = d e / d x``; ``Phi = expm(F dt)`` or its Taylor series, ``F`` analytic at ``x+``),
  ``P- = Phi_e P+ Phi_e^T + T(x-) Q T(x-)^T`` (the scenario's block Q mapped to the chart).
- **Update**: on ``e`` with prior mean 0 and covariance ``P-``, measurement model
  ``h(x- [+] e)`` and Jacobian ``H(x- [+] e) S(x-, e)`` (exact, analytic), by the EKF
  kernel or by the IEKF kernel (Gauss-Newton on the MAP cost with the same step control
  and stopping; the chart keeps ``|q| = 1``), after the same feature mask and gate as the
  full-state filters (``relnav.gated_model``).
- **Reset**: ``x+ = x- [+] e+``; the covariance is kept (the reset Jacobian differs from
  the identity by the attitude correction, 1e-3 after the first steps; left out, as in
  Markley & Crassidis 2014, 7.2).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..config.resolve import FilterSetup, Setup
from ..core import aligned, dynamics, errorstate as es, jacobians
from ..core import kalman as kf
from ..core.orbit import leader_kinematics
from . import relnav

Array = NDArray[np.float64]


CHARTS = {"attitude": es, "aligned": aligned}  # each has chart, local, chart_jacobian, error_map


def chart_of(fs: FilterSetup):
    """The chart module of a filter's error state (the attitude chart for ``full``: NEES, UKF sigma points)."""
    return CHARTS.get(fs.error_state, es)


def to_error_covariance(x: Array, P: Array, fs: FilterSetup) -> Array:
    """``T P T^T``: a full-state covariance in the filter's error-state coordinates at ``x``."""
    T = chart_of(fs).error_map(x)
    return T @ P @ np.swapaxes(T, -1, -2)


def error_process_noise(x: Array, Q_diag: Array, chart=es) -> Array:
    """``T(x) diag(Q) T(x)^T`` (``B, n-1, n-1``) in the error state of ``chart``."""
    T = chart.error_map(x)
    return (T * Q_diag[..., None, :]) @ np.swapaxes(T, -1, -2)


def predict(x: Array, P: Array, t: float, fs: FilterSetup, setup: Setup) -> tuple[Array, Array]:
    """``(x-, P-)`` at ``t + dt``; ``P`` is the error-state covariance ``(B, n-1, n-1)``."""
    ch = chart_of(fs)
    lk = leader_kinematics(setup.orbit, t)
    F = jacobians.F(x, lk.r, lk.nu_dot, lk.nu_ddot, setup.orbit.mu)
    Phi = kf.transition_matrix(F, setup.dt, fs.transition, fs.taylor_order)
    x_pred = relnav.renormalize(dynamics.propagate(x, t, setup.dt, setup.orbit, fs.substeps))
    Phi_e = ch.error_map(x_pred) @ Phi @ ch.chart_jacobian(x)
    Q = relnav.process_noise(x, P, t, fs, setup)
    P_pred = Phi_e @ P @ np.swapaxes(Phi_e, -1, -2) + error_process_noise(x_pred, Q, ch)
    return x_pred, kf.symmetrize(P_pred)


def error_measurement(measure, x_ref: Array, rows_all: Array, chart=es):
    """``measure_eps(e, rows, jac)``: ``h(x_ref [+] e)`` and ``H S`` for the trials ``rows``."""

    def measure_eps(eps: Array, rows: Array, jac: bool = True):
        ref = x_ref[np.searchsorted(rows_all, rows)]
        x = chart.chart(ref, eps)
        hx, H = measure(x, rows, jac=jac)
        return hx, (H @ chart.chart_jacobian(ref, eps) if jac else None)

    return measure_eps


def update(x: Array, P: Array, step: relnav.StepMeasurement, rows: Array, fs: FilterSetup, setup: Setup,
           model=None) -> kf.Update:  # fmt: skip
    """The error-state update and reset at one step (feature mask, gate, EKF or iterated update); ``model`` as in
    ``relnav.update`` (the full state's ``measure``, seen through the chart)."""
    ch = chart_of(fs)
    e0 = np.zeros(P.shape[:-1])
    measure = error_measurement((model or relnav.measurement_model)(setup, step), x, rows, ch)
    measure, R, y, rejected, used, P = relnav.gated_model(e0, P, measure, step, rows, fs, setup)
    u = relnav.kalman_update(e0, P, y, measure, R, rows, fs, setup, step)
    return relnav.GatedUpdate(ch.chart(x, u.x), u.P, u.nu, u.nis, u.iterations, u.converged, rejected, used)
