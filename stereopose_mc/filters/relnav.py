"""One filter step of the relative-navigation problem, batched over trials.

This layer binds the generic kernels of ``core.kalman`` to the model of docs/model.md:

- prediction from the posterior at ``t_{k-1}``: ``x-`` by RK4 (``substeps`` per step)
  of ``core.dynamics.f``; ``F`` evaluated at the posterior ``x+(t_{k-1})``;
  ``Phi = expm(F dt)`` or its Taylor series; ``P- = Phi P Phi^T + Q``;
- measurement at ``t_k``: per visible feature ``[u_R, v_R, u_L, v_L, du_R, dv_R,
  du_L, dv_L]`` (+ ``d``), feature-major, then (when enabled) the 3 rows of the inertia
  pseudo-measurement with observed value 0; ``R`` is diagonal from the filter's own
  standard deviations;
- the quaternion is renormalized after every prediction and every update (IEKF
  iterates are not: ``h`` does not depend on the quaternion's norm); the covariance is
  not projected.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..config.resolve import FilterSetup, Setup
from ..core import camera, dynamics, jacobians, state as st
from ..core import errorstate as es
from ..core import kalman as kf
from ..core import layout as lay
from ..core.inertia import h_pseudo, pseudo_second_order_variance, rate_second_order_variance
from ..core.orbit import leader_kinematics
from . import gating

Array = NDArray[np.float64]


def renormalize(x: Array) -> Array:
    """Copy of ``x`` with its quaternion block normalized."""
    x = x.copy()
    q = x[..., st.QUAT]
    x[..., st.QUAT] = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return x


def predict(x: Array, P: Array, t: float, fs: FilterSetup, setup: Setup) -> tuple[Array, Array]:
    """``(x-, P-)`` at ``t + dt`` from the posterior ``(x, P)`` at ``t``."""
    lk = leader_kinematics(setup.orbit, t)
    F = jacobians.F(x, lk.r, lk.nu_dot, lk.nu_ddot, setup.orbit.mu)
    Phi = kf.transition_matrix(F, setup.dt, fs.transition, fs.taylor_order)
    x_pred = renormalize(dynamics.propagate(x, t, setup.dt, setup.orbit, fs.substeps))
    return x_pred, kf.predict_covariance(P, Phi, process_noise(x, P, t, fs, setup))


def process_noise(x: Array, P: Array, t: float, fs: FilterSetup, setup: Setup) -> Array:
    """The diagonal of the prediction's ``Q`` per trial ``(b, n)`` from the posterior ``(x, P)`` at ``t``:
    ``fs.Q_diag`` (a read-only broadcast without ``fs.second_order``), and with it ``omega``'s entries add ``dt^2``
    times the variance the Euler term's linearization leaves out (``core.inertia.rate_second_order_variance``;
    ``P`` the full state's or an error state's, as ``pseudo_linearization_variance``). The same shape as the
    compiled twin's (``filters.compiled.process_noise``)."""
    if not fs.second_order:
        return np.broadcast_to(fs.Q_diag, (x.shape[0], fs.Q_diag.size))
    w = omega_rows(x, P)
    nu_dot = leader_kinematics(setup.orbit, t).nu_dot
    Q = np.tile(fs.Q_diag, (x.shape[0], 1))
    Q[:, st.OMEGA] += setup.dt**2 * rate_second_order_variance(x, P[..., w, w], P[..., -2:, -2:], P[..., -2:, w],
                                                                nu_dot)  # fmt: skip
    return Q


def channel_variances(fs: FilterSetup, disparity: bool) -> Array:
    """The filter's R diagonal for one feature (8 or 9,)."""
    v = [fs.sigma_image**2] * 4 + [fs.sigma_flow**2] * 4
    if disparity:
        v.append(fs.sigma_disparity**2)
    return np.asarray(v)


@dataclass(frozen=True)
class StepMeasurement:
    """What the filter sees at one step, for a batch of trials."""

    y: Array  # (B, m) stacked measurement (pseudo rows observed as 0)
    alpha: Array  # (B, 3) measured angular acceleration (used only with the pseudo rows)
    visible: Array  # (N,) bool: features in view at this step
    t: float
    alpha_var: Array | None = None  # (B, 3) per-trial R of the pseudo rows; None: the filter's sigma_alpha^2
    feature_var: Array | None = None  # (B, N, C) per-trial additions to every feature's R (second order); None: none
    feature_mask: Array | None = None  # (B, n_visible) bool: per trial, the visible features measured (faults)
    # (B, n_visible) bool: per trial, the features of the stack in its own view, where ``visible`` is the union of a
    # dispersed batch's views (one compiled update of the batch: ``mc.trial._update``; ``feature_mask`` then
    # within it); None: every trial sees every feature of ``visible``
    offered: Array | None = None


@dataclass(frozen=True)
class GatedUpdate(kf.Update):
    """An update with its feature bookkeeping (sensor faults and gating)."""

    rejected: Array = field(default=None)  # (b,) int: features rejected by the gate
    features_used: Array = field(default=None)  # (b,) int: features that entered the update
    # (b, n, n) square root R of P = R^T R where the compiled update gives it: the rows of P's upper Cholesky
    # factor in reverse order (core.kernels.update.iekf_update_batch; NaN at [i, n - 1, 0] where it does not);
    # None: not given (the NEES then factorize P themselves)
    P_factor: Array | None = field(default=None)
    # (b, 8) the posterior's NEES (core.kernels.consistency.KEYS) and (b,) whether P is positive definite (1.0/0.0),
    # evaluated by the compiled update against the truth it was given (mc.trial); NaN rows: not evaluated there
    # (the trials numpy updated, or no truth given); None: none evaluated
    nees: Array | None = field(default=None)
    nees_pd: Array | None = field(default=None)
    # (b, 28) the posterior's per-axis errors and their variances (core.kernels.update: in the aligned chart, from the
    # blocks of its block NEES; mc.trial.axis_errors before its units), NaN rows: not evaluated; None: none
    axes: Array | None = field(default=None)


def measurement_model(setup: Setup, step: StepMeasurement):
    """The ``measure(x, rows, jac)`` callable of ``core.kalman`` for this step."""
    lk = leader_kinematics(setup.orbit, step.t)
    vis = np.flatnonzero(step.visible)

    def measure(x: Array, rows: Array, jac: bool = True):
        h = camera.h_features(x, setup.baseline, setup.disparity, setup.focal)[:, vis]
        B = x.shape[0]
        parts = [h.reshape(B, -1)]
        Hs = []
        if jac:
            Hf = jacobians.H_features(x, setup.baseline, setup.disparity, setup.focal)[:, vis]
            Hs.append(Hf.reshape(B, -1, x.shape[-1]))
        if setup.pseudo:
            a = step.alpha[rows]
            parts.append(h_pseudo(x, a, lk.nu_dot, lk.nu_ddot))
            if jac:
                Hs.append(jacobians.H_pseudo(x, a, lk.nu_dot, lk.nu_ddot))
        hx = np.concatenate(parts, axis=-1)
        return hx, (np.concatenate(Hs, axis=-2) if jac else None)

    return measure


def omega_rows(x: Array, P: Array) -> slice:
    """``omega``'s rows in ``P``: the full state's (``P (b, n, n)``) or an error state's (``(b, n-1, n-1)``)."""
    at = lay.OMEGA if P.shape[-1] == x.shape[-1] else lay.E_OMEGA
    return slice(at, at + lay.VEC)


def pseudo_linearization_variance(x: Array, P: Array, setup: Setup, t: float) -> Array:
    """``(b, 3)``: the variance the pseudo rows' linearization at ``x`` leaves out (``core.inertia``), from the
    ``omega`` and ``k`` blocks of ``P`` (``(b, n, n)`` or an error state's ``(b, n-1, n-1)``: ``omega`` sits at the same
    offset and ``k`` last in every chart, both additive)."""
    w = omega_rows(x, P)
    nu_dot = leader_kinematics(setup.orbit, t).nu_dot
    return pseudo_second_order_variance(x, P[..., w, w], P[..., -2:, -2:], P[..., -2:, w], nu_dot)


def measurement_noise(fs: FilterSetup, setup: Setup, n_visible: int, alpha_var: Array | None = None,
                      feature_var: Array | None = None) -> Array:  # fmt: skip
    """The filter's R diagonal, ``(m,)``, or ``(b, m)`` with per-trial pseudo rows ``alpha_var (b, 3)`` and/or
    per-trial additions ``feature_var (b, n_visible, C)`` to the features' rows."""
    r = np.tile(channel_variances(fs, setup.disparity), n_visible)
    if feature_var is not None:
        r = r + feature_var.reshape(feature_var.shape[0], -1)
    if not setup.pseudo:
        return r
    if alpha_var is None:
        return np.concatenate([r, np.broadcast_to(fs.sigma_alpha**2, r.shape[:-1] + (3,))], axis=-1)
    return np.concatenate([np.broadcast_to(r, alpha_var.shape[:-1] + r.shape[-1:]), alpha_var], axis=-1)


def flow_linearization_variance(x: Array, P: Array, setup: Setup) -> Array:
    """``(b, N, C)``: the variance the image-velocity rows' linearization at ``x`` leaves out (``core.camera``), from
    the ``omega`` block of ``P`` and each feature point's ``3 x 3`` block (the full state's or an error state's: the
    points are additive in every chart; the aligned chart's, in the rotated body frame, to first order the same)."""
    N = st.n_points(x.shape[-1])
    w = omega_rows(x, P)
    p0 = (st.points_slice(N) if P.shape[-1] == x.shape[-1] else es.points_slice(N)).start
    idx = p0 + np.arange(3 * N).reshape(N, 3)
    P_pp = P[:, idx[:, :, None], idx[:, None, :]]  # (b, N, 3, 3)
    return camera.flow_second_order_variance(x, P[..., w, w], P_pp, setup.baseline, setup.disparity, setup.focal)


def stack_measurement(y_feat: Array, visible: Array, pseudo: bool) -> Array:
    """``(B, m)`` from per-feature measurements ``(B, N, C)`` of the visible features (written into one new array:
    this runs at every step of every chunk)."""
    B, N, C = y_feat.shape
    nv = int(np.count_nonzero(visible))
    y = np.zeros((B, nv * C + (3 if pseudo else 0)))
    y[:, : nv * C].reshape(B, nv, C)[...] = y_feat if nv == N else y_feat[:, visible]
    return y


def update(x: Array, P: Array, step: StepMeasurement, rows: Array, fs: FilterSetup, setup: Setup,
           model=None) -> kf.Update:  # fmt: skip
    """The filter's measurement update (EKF or IEKF) at one step.

    ``model(setup, step)``: the step's ``measure`` (default ``measurement_model``; ``filters.compiled`` passes its
    compiled twin when it leaves a trial to this update)."""
    measure = (model or measurement_model)(setup, step)
    measure, R, y, rejected, used, P = gated_model(x, P, measure, step, rows, fs, setup)
    u = kalman_update(x, P, y, measure, R, rows, fs, setup, step)
    return GatedUpdate(renormalize(u.x), u.P, u.nu, u.nis, u.iterations, u.converged, rejected, used)


def gated_model(x: Array, P: Array, measure, step: StepMeasurement, rows: Array, fs: FilterSetup, setup: Setup):
    """``(measure, R, y, rejected, used, P)`` after the tracker's feature mask and the filter's gate (``P`` the
    prior the update uses: inflated where the gate found the filter overconfident, ``gating.robust_gate``).

    ``measure(x, rows, jac)`` is the step's model in the filter's own coordinates (the full
    state, or an error state with ``x`` its zero and ``P`` its covariance).
    """
    R = measurement_noise(fs, setup, int(step.visible.sum()), None if step.alpha_var is None else step.alpha_var[rows],
                          None if step.feature_var is None else step.feature_var[rows][:, step.visible])
    y = step.y[rows]
    nvis = int(step.visible.sum())
    C = channel_variances(fs, setup.disparity).size
    keep = None if step.feature_mask is None else step.feature_mask[rows]
    rejected = np.zeros(rows.size, int)
    if fs.gate_probability is not None and nvis:
        hx, H = measure(x, rows, jac=True)
        d2 = gating.distances2(y - hx, gating.linearized_blocks(H, P, R, nvis, C))
        keep, rejected, lam = gating.robust_gate(d2, fs.gate_probability, C, keep, fs.gate_inflate)
        P = gating.inflated(P, lam)
    if keep is not None:
        measure = gating.masked_measure(measure, step.y, rows, keep, C)
    used = np.full(rows.size, nvis) if keep is None else keep.sum(axis=-1)
    return measure, R, y, rejected, used, P


def first_update(setup: Setup, step: StepMeasurement) -> bool:
    """True at the first update (``t = dt``)."""
    return step.t <= setup.dt * (1 + 1e-9)


def iterated_at(fs: FilterSetup, setup: Setup, step: StepMeasurement) -> bool:
    """True when this update runs the Gauss-Newton iterations (``fs.iteration``: the IEKF always; the MEKF when
    ``iterated``; the EKF and the UKF only at the first update with ``first_update: iterated``)."""
    return fs.iteration(first_update(setup, step)) is not None


def kalman_update(x, P, y, measure, R, rows, fs: FilterSetup, setup: Setup, step: StepMeasurement) -> kf.Update:
    """The EKF or iterated (Gauss-Newton) update of ``core.kalman`` that ``fs`` asks for at this step."""
    it = fs.iteration(first_update(setup, step))
    if it is None:
        return kf.ekf_update(x, P, y, measure, R, rows)
    return kf.iekf_update(x, P, y, measure, R, rows, tol=it.tolerance, max_iter=it.max_iterations,
                          step_control=it.step_control, stopping=it.stopping)  # fmt: skip
