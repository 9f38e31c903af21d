"""Multiplicative (error-state) EKF of the relative-navigation problem, batched over trials.

The estimate keeps the full state ``x (B, n)`` with its unit quaternion; the covariance
is that of the error state ``eps (n - 1)`` of ``core.errorstate`` (attitude as a
3-vector ``a``, ``q = dq(a) (x) q_hat``), so it has no quaternion-norm direction.

- **Prediction**: ``x- = RK4(f, x+)`` as the EKF; the error-state transition is the full
  one seen through the chart, ``Phi_eps = T(x-) Phi S(x+)`` (``S = d x / d eps`` at
  ``eps = 0``, ``T = d eps / d x``; ``Phi = expm(F dt)`` or its Taylor series, ``F`` analytic
  at ``x+``), ``P- = Phi_eps P+ Phi_eps^T + T(x-) Q T(x-)^T`` (the scenario's block Q
  mapped to the error state: ``4 q`` rad^2 on the attitude).
- **Update**: on ``eps`` with prior mean 0 and covariance ``P-``, measurement model
  ``h(x- [+] eps)`` and Jacobian ``H(x- [+] eps) S(x-, eps)`` (exact, analytic), by the EKF
  kernel or, with ``iterated``, by the IEKF kernel (Gauss-Newton on the MAP cost with the
  same step control and stopping; no renormalization needed: the chart keeps ``|q| = 1``).
- **Reset**: ``x+ = x- [+] eps+``; the covariance is kept (the reset Jacobian
  ``I - [a/2 x]`` on the attitude block differs from the identity by the attitude
  correction, 1e-3 after the first steps; left out, as in Markley & Crassidis 2014, 7.2).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..config.resolve import FilterSetup, Setup
from ..core import dynamics, errorstate as es, jacobians
from ..core import kalman as kf
from ..core.orbit import leader_kinematics
from . import relnav

Array = NDArray[np.float64]


def error_process_noise(x: Array, Q_diag: Array) -> Array:
    """``T(x) diag(Q) T(x)^T`` (``B, n-1, n-1``)."""
    T = es.error_map(x)
    return (T * Q_diag[..., None, :]) @ np.swapaxes(T, -1, -2)


def predict(x: Array, P: Array, t: float, fs: FilterSetup, setup: Setup) -> tuple[Array, Array]:
    """``(x-, P-)`` at ``t + dt``; ``P`` is the error-state covariance ``(B, n-1, n-1)``."""
    lk = leader_kinematics(setup.orbit, t)
    F = jacobians.F(x, lk.r, lk.nu_dot, lk.nu_ddot, setup.orbit.mu)
    Phi = kf.transition_matrix(F, setup.dt, fs.transition, fs.taylor_order)
    x_pred = relnav.renormalize(dynamics.propagate(x, t, setup.dt, setup.orbit, fs.substeps))
    Phi_e = es.error_map(x_pred) @ Phi @ es.chart_jacobian(x)
    P_pred = Phi_e @ P @ np.swapaxes(Phi_e, -1, -2) + error_process_noise(x_pred, fs.Q_diag)
    return x_pred, kf.symmetrize(P_pred)


def error_measurement(measure, x_ref: Array, rows_all: Array):
    """``measure_eps(eps, rows, jac)``: ``h(x_ref [+] eps)`` and ``H S`` for the trials ``rows``."""

    def measure_eps(eps: Array, rows: Array, jac: bool = True):
        ref = x_ref[np.searchsorted(rows_all, rows)]
        x = es.chart(ref, eps)
        hx, H = measure(x, rows, jac=jac)
        return hx, (H @ es.chart_jacobian(ref, eps) if jac else None)

    return measure_eps


def update(x: Array, P: Array, step: relnav.StepMeasurement, rows: Array, fs: FilterSetup, setup: Setup) -> kf.Update:
    """The MEKF's measurement update and reset at one step."""
    measure = error_measurement(relnav.measurement_model(setup, step), x, rows)
    R = relnav.measurement_noise(fs, setup, int(step.visible.sum()), None if step.alpha_var is None else step.alpha_var[rows])
    y = step.y[rows]
    e0 = np.zeros(P.shape[:-1])
    if fs.max_iterations > 1:
        u = kf.iekf_update(e0, P, y, measure, R, rows, tol=fs.tolerance, max_iter=fs.max_iterations,
                           step_control=fs.step_control, stopping=fs.stopping)  # fmt: skip
    else:
        u = kf.ekf_update(e0, P, y, measure, R, rows)
    return kf.Update(es.chart(x, u.x), u.P, u.nu, u.nis, u.iterations, u.converged)
