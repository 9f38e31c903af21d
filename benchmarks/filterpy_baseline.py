"""The per-trial baseline: the relative-navigation EKF written with FilterPy, as a user would.

``filterpy.kalman.ExtendedKalmanFilter`` predicts the state linearly (``x = F x`` in
``predict_x``) and uses ``F`` as the discrete transition matrix of the covariance
(``P = F P F^T + Q``). So, per step ``k-1 -> k`` of one trial:

1. ``F <- expm(J dt)`` with ``J = core.jacobians.F`` at the posterior ``x+(t_{k-1})``
   (``scipy.linalg.expm``);
2. ``predict()`` with ``predict_x`` overridden to integrate the nonlinear dynamics
   (``core.dynamics.propagate``, the filter's RK4 substeps) and renormalize ``q``;
3. ``update(z, HJacobian, Hx, R)`` with ``z`` the visible features' 8 channels and the
   3 zero rows of the inertia pseudo-measurement; ``Hx``/``HJacobian`` stack
   ``core.camera.h_features`` / ``core.jacobians.H_features`` of the visible features and
   ``core.inertia.h_pseudo`` / ``core.jacobians.H_pseudo``; FilterPy's gain uses
   ``inv(S)`` and its covariance the Joseph form; then ``q`` is renormalized;
4. the errors against the truth. Every trial runs all its steps (a user's loop has no
   divergence test); only a non-finite state or a singular ``S`` stops a trial, since
   it cannot go on. (The engine freezes a trial at its divergence step, so compare
   throughputs per trial-step when trials diverge.)

A Python loop over steps and trials. FilterPy has no iterated EKF: only the EKF is
compared (against our EKF). The only differences from our EKF are ``expm`` for the
transition (ours: order-4 Taylor by default) and ``inv(S)`` for the gain (ours: ``solve``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from scipy.linalg import expm

from stereopose_mc.core import camera, dynamics, jacobians, state as st
from stereopose_mc.core.inertia import h_pseudo
from stereopose_mc.core.layout import n_measurements
from stereopose_mc.core.orbit import leader_kinematics
from stereopose_mc.filters import relnav
from stereopose_mc.mc.trial import errors


class RelNavEKF(ExtendedKalmanFilter):
    """FilterPy's EKF whose state prediction integrates the relative dynamics."""

    def __init__(self, n: int, m: int, orbit, dt: float, substeps: int):
        super().__init__(dim_x=n, dim_z=m)
        self.orbit, self.dt, self.substeps = orbit, dt, substeps
        self.t = 0.0  # time of the posterior being propagated

    def predict_x(self, u=0) -> None:
        x = dynamics.propagate(self.x[:, 0], self.t, self.dt, self.orbit, self.substeps)
        x[st.QUAT] /= np.linalg.norm(x[st.QUAT])
        self.x = x[:, None]


def hx(x: np.ndarray, vis: np.ndarray, alpha: np.ndarray, nu_dot: float, nu_ddot: float, setup) -> np.ndarray:
    """Predicted measurement ``(m, 1)``: visible features' channels, then the 3 pseudo rows."""
    xf = x[:, 0]
    h = camera.h_features(xf, setup.baseline, setup.disparity, setup.focal)[vis].ravel()
    parts = [h]
    if setup.pseudo:
        parts.append(h_pseudo(xf, alpha, nu_dot, nu_ddot))
    return np.concatenate(parts)[:, None]


def h_jacobian(x: np.ndarray, vis: np.ndarray, alpha: np.ndarray, nu_dot: float, nu_ddot: float, setup) -> np.ndarray:
    """Jacobian ``(m, n)`` of ``hx``."""
    xf = x[:, 0]
    n = xf.size
    H = jacobians.H_features(xf, setup.baseline, setup.disparity, setup.focal)[vis].reshape(-1, n)
    parts = [H]
    if setup.pseudo:
        parts.append(jacobians.H_pseudo(xf, alpha, nu_dot, nu_ddot))
    return np.concatenate(parts, axis=0)


@dataclass
class BaselineRun:
    x_final: np.ndarray  # (T, n) state at the last step run
    errors: np.ndarray  # (T, K+1, 6), NaN after a stop
    stopped_step: np.ndarray  # (T,) step of a non-finite state or singular S, -1 if none
    steps_run: int  # trial-steps executed


def run_trials(x0_hat: np.ndarray, y_feat: np.ndarray, alpha: np.ndarray, visible: np.ndarray, truth, setup,
               fs) -> BaselineRun:  # fmt: skip
    """Run the FilterPy EKF on each trial in turn (inputs as for ``mc.trial.run_filter``)."""
    T, n = x0_hat.shape
    K = setup.steps
    err = np.full((T, K + 1, 6), np.nan)
    stop = np.full(T, -1)
    x_final = np.empty((T, n))
    steps = 0
    Q = np.diag(fs.Q_diag)
    for j in range(T):
        m0 = n_measurements(int(visible[1].sum()), setup.disparity, setup.pseudo)
        ekf = RelNavEKF(n, m0, setup.orbit, setup.dt, fs.substeps)
        ekf.x = x0_hat[j][:, None].copy()
        ekf.P = np.diag(setup.P0_diag)
        ekf.Q = Q
        err[j, 0] = errors(ekf.x[:, 0], truth.x[0])
        for k in range(1, K + 1):
            lk0 = leader_kinematics(setup.orbit, truth.t[k - 1])
            ekf.F = expm(jacobians.F(ekf.x[:, 0], lk0.r, lk0.nu_dot, lk0.nu_ddot, setup.orbit.mu) * setup.dt)
            ekf.t = truth.t[k - 1]
            ekf.predict()
            vis = visible[k]
            lk = leader_kinematics(setup.orbit, truth.t[k])
            z = y_feat[j, k][vis].ravel()
            if setup.pseudo:
                z = np.concatenate([z, np.zeros(3)])
            R = np.diag(relnav.measurement_noise(fs, setup, int(vis.sum())))
            args = (vis, alpha[j, k], lk.nu_dot, lk.nu_ddot, setup)
            steps += 1
            try:
                ekf.update(z[:, None], h_jacobian, hx, R=R, args=args, hx_args=args)
            except (np.linalg.LinAlgError, ValueError):  # singular S, or a non-finite one (scipy's inv refuses it)
                stop[j] = k
                break
            ekf.x[st.QUAT] /= np.linalg.norm(ekf.x[st.QUAT])
            if not (np.isfinite(ekf.x).all() and np.isfinite(ekf.P).all()):
                stop[j] = k
                break
            err[j, k] = errors(ekf.x[:, 0], truth.x[k])
        x_final[j] = ekf.x[:, 0]
    return BaselineRun(x_final, err, stop, steps)
