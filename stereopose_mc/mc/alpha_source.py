"""Angular-acceleration source of the inertia pseudo-measurement (docs/angular-acceleration.md).

The pseudo-measurement needs the relative angular acceleration ``alpha = d omega/dt`` (in
``L``) and its noise variance. ``measurements.inertia_pseudo_measurement.angular_acceleration``
selects where it comes from:

- ``truth_plus_noise`` (default; the thesis's simulation shortcut): the simulator's true
  ``omega_dot`` plus Gaussian noise; the filter's variance is its own ``sigma_alpha^2``;
- ``savitzky_golay``, ``tikhonov``, ``tracking_differentiator``: a causal derivative of
  the filter's *own* estimates of ``omega`` over the newest ``W`` samples (thesis
  appendix B; kernels in ``core.differentiators``); the variance is propagated from the
  estimates' variances (the diagonal of the ``omega`` block of ``P``) through the method,
  treating the samples as independent (see the doc for what that neglects).

The trial loop calls the pure function ``alpha_step`` once per step, in order, for every
step from the first sample on (the tracking differentiator must see every sample).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..config.resolve import FilterSetup, Setup
from ..core import differentiators as dif

Array = NDArray[np.float64]
METHODS = ("truth_plus_noise", "savitzky_golay", "tikhonov", "tracking_differentiator")


@dataclass(frozen=True, eq=False)
class AlphaSource:
    """Settings of the angular-acceleration source, SI units.

    ``sigma_alpha`` (rad/s^2) is the filter's own standard deviation for
    ``truth_plus_noise``; ``sigma_floor`` (rad/s^2) bounds the returned standard
    deviation of the differentiated methods from below. ``td_h0`` is in seconds, ``td_r`` in rad/s^3.
    ``weights`` (the linear methods' ``c (W,)``, 1/s) is derived, not set.
    """

    method: str = "truth_plus_noise"
    dt: float = 1.0
    window: int = 9
    polyorder: int = 2
    tikhonov_lambda: float = 100.0
    tikhonov_order: int = 2
    td_r: float = 0.05
    td_h0: float = 1.5
    sigma_alpha: float = 1e-6
    sigma_floor: float = 1e-9
    weights: Array | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown angular-acceleration source {self.method!r}; one of {METHODS}")
        if not (self.dt > 0 and self.sigma_alpha > 0 and self.sigma_floor > 0):
            raise ValueError("dt, sigma_alpha and sigma_floor must be > 0")
        if self.window < 3:
            raise ValueError(f"window must be >= 3 (got {self.window})")
        c = None
        if self.method == "savitzky_golay":
            c = dif.savgol_weights(self.window, self.polyorder, self.dt)
        elif self.method == "tikhonov":
            c = dif.tikhonov_weights(self.window, self.tikhonov_lambda, self.dt, self.tikhonov_order)
        elif self.method == "tracking_differentiator":
            if not self.td_r > 0:
                raise ValueError(f"td_r must be > 0 (got {self.td_r})")
            dif.td_noise_gain(self.dt, self.td_h0)  # raises if unstable (h0 <= dt/2)
        object.__setattr__(self, "weights", c)

    @property
    def differentiated(self) -> bool:
        """Whether alpha comes from the filter's own estimates (needs the history buffer)."""
        return self.method != "truth_plus_noise"

    @property
    def warmup_steps(self) -> int:
        """Samples needed before the first alpha: ``W`` for differentiated methods, 1 otherwise."""
        return self.window if self.differentiated else 1


def alpha_source_of(setup: Setup, fs: FilterSetup) -> AlphaSource:
    """The source of a scenario for one filter (``fs.sigma_alpha`` is that filter's own ``sigma_alpha``)."""
    return AlphaSource(
        method=setup.alpha_method,
        dt=setup.dt,
        window=setup.alpha_window,
        polyorder=setup.alpha_polyorder,
        tikhonov_lambda=setup.alpha_tikhonov_lambda,
        tikhonov_order=setup.alpha_tikhonov_order,
        td_r=setup.alpha_td_r,
        td_h0=setup.alpha_td_h0,
        sigma_alpha=fs.sigma_alpha,
        sigma_floor=setup.alpha_sigma_floor,
    )


def alpha_step(
    source: AlphaSource,
    k: int,
    omega_hist: Array,
    var_hist: Array,
    td_state: Array | None,
    alpha_meas_truth: Array,
) -> tuple[Array, Array, Array | None]:
    """``(alpha (B, 3), sigma2 (B, 3), td_state)`` for the sample where alpha is needed.

    - ``k``: index of the newest sample of the history, counting the first sample the
      caller ever pushed as 0 (so ``k + 1`` samples exist);
    - ``omega_hist (B, W', 3)``: the filter's own estimates of ``omega`` (rad/s, in ``L``),
      oldest first, the newest (``[:, -1]``) at the sample where alpha is needed;
      ``W' >= W`` (only the newest ``W`` are used); entries before the first sample may
      hold anything (NaN is fine);
    - ``var_hist (B, W', 3)``: their variances (diagonal of the ``omega`` block of ``P``);
    - ``td_state (B, 5, 3)`` or ``None``: the tracking differentiator's state returned by
      the previous call (its ``[x1, x2]`` and their linear-zone error covariance, see
      ``_td``; ``None``, or anything, at ``k == 0``: it restarts from the newest sample);
      other methods return it unchanged;
    - ``alpha_meas_truth (B, 3)``: the simulator's noisy alpha, used by ``truth_plus_noise``.

    Warm-up: while fewer than ``W`` samples exist (``k < W - 1``), a differentiated
    method returns ``alpha = sigma2 = NaN`` for every trial, and the trial loop must
    skip the pseudo rows at that step (it is the same step for every trial). A trial
    whose window holds a non-finite sample also gets NaN (only diverged trials do).
    The tracking differentiator still advances its state during the warm-up, so call
    this at every step from ``k = 0``.

    ``sigma2`` is per ``L``-axis: ``truth_plus_noise``: ``sigma_alpha^2``;
    linear methods: ``sum_j c_j^2 var_j``; tracking differentiator: ``S22`` of its
    carried linear-zone error covariance (all samples since ``k = 0``, the initial
    transient included); the differentiated ones are
    floored at ``sigma_floor^2``. For the filter's R of the pseudo rows (which are in ``T``) use
    ``pseudo_row_variance``.
    """
    B = alpha_meas_truth.shape[0]
    if not source.differentiated:
        alpha = np.array(alpha_meas_truth, dtype=float, copy=True)
        sigma2 = np.full((B, 3), source.sigma_alpha**2)
        return alpha, sigma2, td_state
    W = source.window
    if omega_hist.shape[-2] < W or var_hist.shape != omega_hist.shape:
        raise ValueError(f"need omega_hist and var_hist of equal shape (B, >= {W}, 3); got "
                         f"{omega_hist.shape} and {var_hist.shape}")  # fmt: skip
    w = omega_hist[:, -W:, :]
    v = var_hist[:, -W:, :]
    if source.method == "tracking_differentiator":
        alpha, sigma2, td_state = _td(source, k, omega_hist[:, -1, :], var_hist[:, -1, :], td_state)
    else:
        alpha = dif.apply_weights(source.weights, w)
        sigma2 = dif.weights_variance(source.weights, v)
    sigma2 = np.maximum(sigma2, source.sigma_floor**2)
    if k < W - 1:
        return np.full((B, 3), np.nan), np.full((B, 3), np.nan), td_state
    bad = ~(np.isfinite(w).all(axis=(-2, -1)) & np.isfinite(v).all(axis=(-2, -1)) & np.isfinite(alpha).all(axis=-1))
    alpha = np.where(bad[:, None], np.nan, alpha)
    sigma2 = np.where(bad[:, None], np.nan, sigma2)
    return alpha, sigma2, td_state


TD_STATE_ROWS = 5  # [x1, x2, S11, S12, S22]


def _td(source: AlphaSource, k: int, v: Array, var: Array, td_state: Array | None) -> tuple[Array, Array, Array]:
    """Tracking differentiator: consume the newest sample ``v (B, 3)`` of variance ``var (B, 3)``.

    ``td_state (B, 5, 3)``: rows 0-1 the differentiator's state ``[x1, x2]``, rows 2-4
    its linear-zone error covariance ``[S11, S12, S22]`` (``core.differentiators``). At
    ``k == 0`` (or ``None``) it starts from the sample (``x = [v, 0]``, ``S = diag(var, 0)``).
    """
    if td_state is None or k == 0:
        state = dif.td_init(v)
        S = dif.td_covariance_init(var)
        return state[:, 1, :].copy(), S[:, 2, :].copy(), np.concatenate([state, S], axis=-2)
    if td_state.shape[-2:] != (TD_STATE_ROWS, 3):
        raise ValueError(f"td_state must be (B, {TD_STATE_ROWS}, 3); got {td_state.shape}")
    state, alpha = dif.td_step(td_state[:, :2, :], v, source.dt, source.td_r, source.td_h0)
    S = dif.td_covariance_step(td_state[:, 2:, :], var, source.dt, source.td_h0)
    return alpha, S[:, 2, :].copy(), np.concatenate([state, S], axis=-2)


def pseudo_row_variance(sigma2: Array, floor: float = 0.0) -> Array:
    """The filter's R diagonal ``(B, 3)`` for the pseudo rows from per-``L``-axis variances ``sigma2 (B, 3)``.

    The pseudo rows are ``D^T (alpha + ...)`` (in ``T``), so their noise covariance is
    ``D^T diag(sigma2) D``, not diagonal unless ``sigma2`` is isotropic. The diagonal
    ``max_i sigma2_i I_3`` bounds it from above (``D^T diag(s) D <= max(s) I``) and is
    exact when the axes agree (always for ``truth_plus_noise``).
    """
    m = np.maximum(np.max(sigma2, axis=-1, keepdims=True), floor**2)
    return np.broadcast_to(m, sigma2.shape).copy()
