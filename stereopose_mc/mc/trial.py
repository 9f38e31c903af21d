"""A chunk of Monte Carlo trials: initial draws, the filter loop, per-trial summaries.

All trials of a chunk step through time together (arrays ``(B, n)``, ``(B, n, n)``).
Each filter of the scenario sees the same initial estimate and the same measurements
in a trial (paired comparison). Two things can happen to a trial (docs/filters.md, Lost
and inconsistent trials), and neither stops the others:

- **lost**: what the filter itself can detect. A non-finite state or covariance, a
  covariance that is not positive definite (Cholesky fails), a linear-algebra failure in
  the update, or, from ``nis_start_s`` on, its NIS averaged over the last
  ``nis_window_steps`` steps exceeds ``nis_ratio`` times the measurement dimension, or
  (gated filters) its gate rejected at least ``gated_fraction`` of the features it was
  given at every one of those steps (a filter locked out by its own gate), or it measured
  no feature at any of those steps (none in view or delivered). The filter
  stops there: the trial is frozen at that step, its later errors are NaN.
- **inconsistent**: what only the truth reveals. An error beyond the scenario's
  ``divergence`` bounds (``rho_m``, ``rho_dot_mps``, ``omega_degps``, ``k``), or a NEES far
  beyond its claimed covariance (``mc/divergence.py``). A flag only, with its first step
  and reason: the filter goes on to the end (a chaser cannot see the truth) and its
  errors count.
"""

from __future__ import annotations

import dataclasses
import functools
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from ..config.resolve import FilterSetup, Setup
from ..core import aligned
from ..core import errorstate as es
from ..core import quaternion as qt
from ..core import state as st
from ..core import kalman as kf
from ..filters import estimators, registry, relnav
from ..filters import slots as sl
from ..filters.initialization import measurement_start
from .divergence import inconsistent_reasons
from .alpha_source import alpha_source_of, alpha_step, pseudo_row_variance
from ..sim import measurements as meas
from ..sim.faults import Faults, apply_faults
from ..sim.truth import Truth
from ..rundir.tables import AXES

Array = NDArray[np.float64]
RAD2DEG = 180.0 / np.pi
# SI -> the units of rundir.tables.AXIS_UNITS (rho, rho_dot as they are; omega and the attitude error in degrees)
_AXIS_SCALE = np.array([1.0] * 6 + [RAD2DEG] * 6 + [1.0] * 2)


@dataclass(frozen=True)
class Bounds:
    """Divergence bounds (the scenario's ``divergence`` block, in its units)."""

    rho_m: float = 1000.0
    rho_dot_mps: float = 100.0
    omega_degps: float = 180.0
    k: float = 20.0
    nis_ratio: float = 100.0
    nis_window_steps: int = 10
    nis_start_s: float = 10.0
    gated_fraction: float = 0.5
    sigma_ratio: float = 30.0  # 'inconsistent': a block's error over its claimed sigma (mc/divergence.py)
    nees_factor: float = 10.0  # 'inconsistent': gauge-projected NEES over its chi-square 99.9% bound


def errors(x_hat: Array, x_true: Array) -> Array:
    """The six errors ``(..., 6)``: m, m/s, deg/s, deg, -, - (docs/model.md, thesis 6.46-6.60)."""
    N = st.n_points(x_hat.shape[-1])
    ks = st.k_slice(N)
    d = x_hat - x_true
    return np.stack(
        [
            np.linalg.norm(d[..., st.RHO], axis=-1),
            np.linalg.norm(d[..., st.RHO_DOT], axis=-1),
            np.linalg.norm(d[..., st.OMEGA], axis=-1) * RAD2DEG,
            qt.error_angle(x_true[..., st.QUAT], x_hat[..., st.QUAT]) * RAD2DEG,
            np.abs(d[..., ks][..., 0]),
            np.abs(d[..., ks][..., 1]),
        ],
        axis=-1,
    )


def errors_of(x_hat: Array, x_true: Array, kernels: str = "numpy") -> Array:
    """``errors`` (``(B, 6)``, ``x_hat (B, n)``) on the ``kernels`` path: numpy, or the compiled
    ``core.kernels.consistency.errors`` (the same numbers: tests/core/test_kernels_consistency.py)."""
    if kernels == "compiled":
        from ..core.kernels import consistency

        return consistency.errors(x_hat, x_true)
    return errors(x_hat, x_true)


def positive_definite(P: Array) -> Array:
    """Per-trial Cholesky success ``(B,)``."""
    try:
        np.linalg.cholesky(P)
        return np.ones(P.shape[0], bool)
    except np.linalg.LinAlgError:
        out = np.zeros(P.shape[0], bool)
        for i in range(P.shape[0]):
            try:
                np.linalg.cholesky(P[i])
                out[i] = True
            except np.linalg.LinAlgError:
                pass
        return out


@dataclass
class FilterRun:
    """Outputs of one filter over a chunk (``B`` trials, ``K+1`` steps)."""

    label: str
    errors: Array  # (B, K+1, 6); NaN after divergence
    nees: Array  # (B, K+1)
    nis: Array  # (B, K+1); NaN at step 0
    nis_dof: Array  # (K+1,) measurement dimension, or (B, K+1) with per-trial visibility (dispersed targets)
    iterations: Array  # (B, K+1) int; 0 at step 0
    converged: Array  # (B, K+1) bool
    lost_step: Array  # (B,) int, -1 if not lost (the filter stopped there)
    lost_reason: list[str] = field(default_factory=list)
    nees_parts: dict[str, Array] = field(default_factory=dict)  # nees_<block>, nees_gauge: (B, K+1)
    runtime_s: Array | None = None  # (B,) chunk wall time shared equally
    x_final: Array | None = None  # (B, n)
    P_final: Array | None = None  # (B, n, n) full state, or (B, n-1, n-1) the filter's error state
    dof: Array | None = None  # (B, K+1) per-trial measurement dimension (features dropped or gated out removed)
    gated: Array | None = None  # (B, K+1) int: features rejected by the filter's gate at each step
    k_sigma_ratio: Array | None = None  # (B, 2) final / initial standard deviation of k1, k2
    inconsistent_step: Array | None = None  # (B,) int: first step a truth-based rule fired, -1 if none (a flag only)
    inconsistent_reason: list[str] = field(default_factory=list)
    state_dim: int = 0  # n: the NEES has n - 1 degrees of freedom, the gauge-projected one n - 4 (errorstate.nees_dof)
    # feature slots (filters.slots): per NEES key, its degrees of freedom per trial and step (B, K+1) (only the
    # occupied slots count); None: the fixed errorstate.nees_dof(state_dim)
    nees_dof_steps: dict[str, Array] | None = None
    axis_err: Array | None = None  # (B, K+1, len(AXES)): per-axis error-state components (AXIS_UNITS); NaN once lost
    axis_sigma: Array | None = None  # (B, K+1, len(AXES)): the filter's standard deviation of each

    def __post_init__(self) -> None:
        B = self.lost_step.shape[0]
        if self.inconsistent_step is None:
            self.inconsistent_step = np.full(B, -1)
        if not self.inconsistent_reason:
            self.inconsistent_reason = [""] * B

    @property
    def diverged_step(self) -> Array:
        """Alias of ``lost_step`` (the name before lost and inconsistent were told apart; one release)."""
        return self.lost_step

    @property
    def diverged_reason(self) -> list[str]:
        """Alias of ``lost_reason`` (one release)."""
        return self.lost_reason


def _check(x: Array, P: Array, err: Array, bounds: Bounds, pd: Array | None = None) -> tuple[list[str], list[str]]:
    """Per trial, the reason it is lost and the reason it is inconsistent ('' when healthy).

    Lost: a non-finite state or covariance, or a covariance that is not positive definite
    (what the filter sees). Inconsistent: an error beyond the ``divergence`` bounds (what
    only the truth reveals; a flag, the filter goes on).
    ``pd``: per trial, ``P`` known positive definite (the compiled NEES kernel's Cholesky
    factorization went through); None: checked here by numpy's Cholesky.
    """
    B = x.shape[0]
    lost, incons = [""] * B, [""] * B
    if pd is None:
        finite = np.isfinite(x).all(axis=-1) & np.isfinite(P).all(axis=(-1, -2))
        pd = np.zeros(B, bool)
        if finite.any():
            pd[finite] = positive_definite(P[finite])
    else:  # a positive definite P was finite, with a finite x: only the others are read again
        finite = pd.copy()
        rest = np.flatnonzero(~pd)
        if rest.size:
            finite[rest] = np.isfinite(x[rest]).all(axis=-1) & np.isfinite(P[rest]).all(axis=(-1, -2))
    for i in np.flatnonzero(~pd):  # (not finite implies not pd)
        lost[i] = "non-finite state or covariance" if not finite[i] else "covariance not positive definite"
    lim = np.array([bounds.rho_m, bounds.rho_dot_mps, bounds.omega_degps, np.inf, bounds.k, bounds.k])
    over = err > lim
    names = ("rho", "rho_dot", "omega", "theta", "k1", "k2")
    for i in np.flatnonzero(over.any(axis=-1)):
        j = int(np.argmax(over[i]))
        incons[i] = f"inconsistent: error bound exceeded: e_{names[j]} = {err[i, j]:.3g} > {lim[j]:g}"
    return lost, incons


def run_filter(
    x0_hat: Array, setup: Setup, truth: Truth, y_feat: Array, alpha: Array, visible: Array, fs: FilterSetup, bounds: Bounds,
    kept: Array | None = None,
    P0: Array | None = None,
    kernels: str = "numpy",
    tick: Callable[[int], None] | None = None,
    slots: sl.Schedule | None = None,
    extra_var: Array | None = None,
) -> FilterRun:
    """Run one filter over a chunk of trials.

    ``y_feat (B, K+1, N, C)``, ``alpha (B, K+1, 3)``, ``visible (K+1, N)`` shared or ``(B, K+1, N)`` per trial
    (a dispersed target: ``_update``); ``kept (B, K+1, N)``
    the features the tracker delivered (None: all). Updates at ``t_k, k >= 1``; step 0
    holds the initial estimate's errors. ``kernels``: ``numpy`` (``filters.relnav``) or
    ``compiled`` (``filters.compiled``, the same step on the Numba kernels). ``tick(n, label, lost)``: told of
    every ``n`` trial-steps done (``B`` per step; a chunk's lost trials count as done) and of the ``lost`` trials
    this filter has lost since its last call, for progress.
    ``slots``: the state's point blocks are feature slots (``filters.slots``): at each step, after the prediction,
    slots whose track ended are freed and slots with a new track are initialized from its measurement (``visible``
    leaves those out of the update); the NEES count the occupied slots only. ``extra_var (B, K+1, N, C)``: added to
    the features' R (a track file's own sigmas above the filter's).
    """
    stepper = step_functions(kernels)
    B, n = x0_hat.shape
    K = setup.steps
    err = np.full((B, K + 1, 6), np.nan)
    nis = np.full((B, K + 1), np.nan)
    # measurement dimension per step (and per trial, with per-trial visibility): visible features x channels
    # (+ 3 pseudo rows)
    nis_dof = visible.sum(axis=-1) * y_feat.shape[-1] + (3 if setup.pseudo else 0)
    nis_dof[..., 0] = 0
    dof = np.broadcast_to(nis_dof, (B, K + 1)).copy()
    gated = np.zeros((B, K + 1), np.int64)
    its = np.zeros((B, K + 1), int)
    conv = np.zeros((B, K + 1), bool)
    div_step = np.full(B, -1)
    reasons = [""] * B
    inc_step = np.full(B, -1)  # the truth-based flag: first step and reason, the filter goes on
    inc_reasons = [""] * B
    x = x0_hat.copy()
    P = np.broadcast_to(np.diag(setup.P0_diag), (B, n, n)).copy() if P0 is None else P0.copy()
    P = estimators.initial_covariance(x, P, fs)
    chart = registry.chart(fs)  # the chart of its covariance, in which its NEES are evaluated
    image_var = relnav.channel_variances(fs, setup.disparity)[sl.IMAGE]
    if slots is not None:  # the tracks of step 0 take their slots
        x, P = sl.manage(x, P, chart, slots.born[:, 0], slots.freed(0), y_feat[:, 0], image_var, setup.baseline,
                         setup.focal)  # fmt: skip
    err[:, 0] = errors_of(x, true_state(truth.x, 0, np.arange(B)), kernels)
    # every NEES of every step in one array, in the compiled update's column order (``_nees_keys``), stored at each
    # step by one assignment; ``nees`` and ``parts`` (``FilterRun``'s) are its columns
    keys = _nees_keys()
    nees_all = np.full((B, K + 1, len(keys)), np.nan)
    nees = nees_all[..., keys.index("nees")]
    parts = {k: nees_all[..., keys.index(k)] for k in es.nees_dof(n) if k != "nees"}
    nees_dof = None if slots is None else {k: np.full((B, K + 1), d) for k, d in es.nees_dof(n).items()}
    if slots is None:
        _record_nees(nees_all, np.arange(B), 0, x, P, true_state(truth.x, 0, np.arange(B)), chart, kernels)
    else:
        _record_slot_nees(nees_all, nees_dof, slots, np.arange(B), 0, x, P, truth.x, chart)
    ax_err = np.full((B, K + 1, len(AXES)), np.nan)
    ax_sig = np.full((B, K + 1, len(AXES)), np.nan)
    ax_err[:, 0], ax_sig[:, 0] = axis_errors_of(x, P, true_state(truth.x, 0, np.arange(B)), chart, kernels)
    # angular-acceleration source (docs/angular-acceleration.md): history of the filter's own
    # posterior omega and its variance, newest last; sample 0 is the initial estimate
    src = alpha_source_of(setup, fs)
    w_hist = np.full((B, src.window, 3), np.nan)
    v_hist = np.full((B, src.window, 3), np.nan)
    w_last, v_last = x[:, st.OMEGA].copy(), _omega_var(P)  # every trial's latest posterior omega, its variance
    w_hist[:, -1], v_hist[:, -1] = w_last, v_last
    td_state = None
    all_trials = np.arange(B)
    active = all_trials
    # The active trials' posteriors, in the order of ``active``: the update's own arrays, kept from step
    # to step (no gather into and scatter from ``x, P`` at each step); ``x, P`` receive a trial's
    # posterior when it is lost (frozen there) and the others' at the end.
    x_act, P_act = x, P
    told = 0  # the lost trials ``tick`` has been told of
    as_one = False  # a dispersed batch updated as one, each trial's view a row mask (_update)
    if kernels == "compiled" and visible.ndim == 3 and slots is None:
        from ..filters.compiled import masks_visibility

        as_one = masks_visibility(fs, P.shape[-1])
    for k in range(1, K + 1):
        if tick is not None:
            tick(B, fs.label, B - active.size - told)  # (and the trials this filter lost since, for progress)
            told = B - active.size
        if active.size == 0:
            if tick is not None:
                tick(B * (K - k))
            break
        if truth.filter_orbits is not None:  # perturbed truth: Keplerian model from the leader's osculating orbit
            setup = dataclasses.replace(setup, orbit=truth.filter_orbits[k - 1])
        with np.errstate(all="ignore"):
            xa, Pa = stepper.predict(x_act, P_act, truth.t[k - 1], fs, setup)
            if slots is not None:  # ended tracks free their slots, new ones take theirs
                xa, Pa = sl.manage(xa, Pa, chart, slots.born[active, k], slots.freed(k)[active], y_feat[active, k],
                                   image_var, setup.baseline, setup.focal)  # fmt: skip
        # alpha at t_{k-1} from the posteriors up to t_{k-1} (sample index k-1), used at t_k
        a_k, s2_k, td_state = alpha_step(src, k - 1, w_hist, v_hist, td_state, alpha[:, k])
        pseudo_k = setup.pseudo and bool(np.isfinite(a_k[active]).all())  # False during the warm-up
        setup_k = setup if pseudo_k == setup.pseudo else dataclasses.replace(setup, pseudo=False)
        if not pseudo_k and setup.pseudo:
            nis_dof[..., k] -= 3
        alpha_var = (pseudo_row_variance(np.nan_to_num(s2_k, nan=1.0), src.sigma_floor) if src.differentiated
                     else None)  # None: the filter's sigma_alpha^2  # fmt: skip
        feature_var = None
        if fs.second_order:  # + the variance the flow and pseudo rows' linearization leaves out
            feature_var = np.zeros(y_feat.shape[:1] + y_feat.shape[2:])  # (B, N, C)
            with np.errstate(all="ignore"):
                feature_var[active] = stepper.flow_linearization_variance(xa, Pa, setup_k)
                if pseudo_k:
                    if alpha_var is None:
                        alpha_var = np.full((B, 3), fs.sigma_alpha**2)
                    alpha_var[active] += stepper.pseudo_linearization_variance(xa, Pa, setup_k, truth.t[k])
        if extra_var is not None:
            feature_var = extra_var[:, k] if feature_var is None else feature_var + extra_var[:, k]
        measured = StepData(y_feat[:, k], np.nan_to_num(a_k), truth.t[k], alpha_var, feature_var)
        with np.errstate(all="ignore"):
            x_true_all = true_state(truth.x, k, all_trials)  # (n,) shared, or (B, n) per trial
            x_true_k = x_true_all if x_true_all.ndim == 1 else x_true_all[active]
            u, failed = _update(stepper.update, kernels, xa, Pa, active, measured, visible, kept, k, x_true_all, fs,
                                setup_k, as_one)  # fmt: skip
            e = errors_of(u.x, x_true_k, kernels)
            try:
                if slots is None:
                    v, pd = _posterior_nees(u, x_true_k, chart, kernels)
                else:
                    v, pd = _slot_nees(nees_dof, slots, active, k, u.x, u.P, truth.x, chart), None
            except np.linalg.LinAlgError:
                v, pd = None, None
            bad, incons = _check(u.x, u.P, e, bounds, pd)
        if any(failed):
            bad = [f or b for f, b in zip(failed, bad)]
        x_act, P_act = u.x, u.P
        w_last[active], v_last[active] = u.x[:, st.OMEGA], _omega_var(u.P)
        w_hist = np.concatenate([w_hist[:, 1:], w_last[:, None]], axis=1)  # push the posterior at t_k
        v_hist = np.concatenate([v_hist[:, 1:], v_last[:, None]], axis=1)
        err[active, k] = e
        ax_err[active, k], ax_sig[active, k] = _posterior_axes(u, x_true_k, chart, kernels)
        its[active, k], conv[active, k] = u.iterations, u.converged
        if getattr(u, "features_used", None) is not None:
            dof[active, k] = u.features_used * y_feat.shape[-1] + (3 if pseudo_k else 0)
            gated[active, k] = u.rejected
        nis[active, k] = u.nis
        if v is not None:
            nees_all[active, k] = v
        if k >= bounds.nis_window_steps and truth.t[k - bounds.nis_window_steps + 1] >= bounds.nis_start_s - 1e-9:
            w0 = k - bounds.nis_window_steps + 1
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                ratio = np.nanmean(nis[active, w0 : k + 1] / np.maximum(dof[active, w0 : k + 1], 1), axis=1)
            for j in np.flatnonzero(ratio > bounds.nis_ratio):
                if not bad[j]:
                    bad[j] = (f"filter lost: mean NIS over {bounds.nis_window_steps} steps = "
                              f"{ratio[j]:.3g} x its dimension > {bounds.nis_ratio:g}")  # fmt: skip
            # not one feature offered to the update (in view and delivered; the pseudo rows are fewer than a feature's)
            blind = np.all(dof[active, w0 : k + 1] // y_feat.shape[-1] + gated[active, w0 : k + 1] == 0, axis=1)
            for j in np.flatnonzero(blind):
                if not bad[j]:
                    bad[j] = f"filter lost: no feature measured at any of {bounds.nis_window_steps} steps"
            if fs.gate_probability is not None:
                lock = _gated_out(gated[active, w0 : k + 1], dof[active, w0 : k + 1], y_feat.shape[-1],
                                  bounds.gated_fraction)  # fmt: skip
                for j in np.flatnonzero(lock):
                    if not bad[j]:
                        bad[j] = (f"filter lost: its gate rejected >= {bounds.gated_fraction:g} of the features "
                                  f"at each of {bounds.nis_window_steps} steps")  # fmt: skip
            # the NEES tests for the trials not flagged yet (a trial keeps its first reason: the others' are not read)
            todo = np.flatnonzero(inc_step[active] < 0)
            if todo.size:
                rows_t = active[todo]
                low = None if nees_dof is not None else np.min(nees_all[rows_t, w0 : k + 1], axis=1)  # all NEES at once
                by_nees = inconsistent_reasons(parts, rows_t, w0, k, nees_dof or es.nees_dof(n), bounds.sigma_ratio,
                                               bounds.nees_factor, None if low is None else
                                               {key: low[:, j] for j, key in enumerate(keys)})  # fmt: skip
                for j, d in zip(todo.tolist(), by_nees):
                    incons[j] = incons[j] or d
        for j in np.flatnonzero(inc_step[active] < 0):
            if incons[j]:  # (a flag of its own: a trial lost later, or at this step, keeps it)
                inc_step[active[j]], inc_reasons[active[j]] = k, incons[j]
        lost = [j for j, b in enumerate(bad) if b]  # the trials lost at this step (positions in ``active``)
        if lost:  # their posteriors stay in x, P; the others go on
            for j in lost:
                div_step[active[j]], reasons[active[j]] = k, bad[j]
            err[active[lost], k:] = np.nan
            ax_err[active[lost], k:] = np.nan
            ax_sig[active[lost], k:] = np.nan
            keep = np.ones(active.size, bool)
            keep[lost] = False
            x[active[~keep]], P[active[~keep]] = x_act[~keep], P_act[~keep]
            x_act, P_act = x_act[keep], P_act[keep]
            active = active[keep]
    x[active], P[active] = x_act, P_act
    ks = slice(P.shape[-1] - 2, P.shape[-1])  # k is last in the state and in the error state
    with np.errstate(all="ignore"):
        k_ratio = np.sqrt(np.diagonal(P[:, ks, ks], axis1=-2, axis2=-1) / setup.P0_diag[-2:])
    return FilterRun(fs.label, err, nees, nis, nis_dof, its, conv, div_step, reasons, nees_parts=parts,
                     x_final=x, P_final=P, k_sigma_ratio=k_ratio, dof=dof, gated=gated,
                     inconsistent_step=inc_step, inconsistent_reason=inc_reasons, state_dim=n,
                     axis_err=ax_err, axis_sigma=ax_sig, nees_dof_steps=nees_dof)  # fmt: skip


def _slot_nees(nees_dof: dict[str, Array], slots: sl.Schedule, rows: Array, k: int, x: Array, P: Array,
               x_true: Array, chart: str) -> Array:  # fmt: skip
    """``filters.slots.nees`` of trials ``rows`` at step ``k`` as ``(len(rows), 8)`` in ``_nees_keys``' order; their
    degrees of freedom into ``nees_dof[key][rows, k]``."""
    xt = slots.true_state(true_state(x_true, k, rows), k, rows)
    v, dof = sl.nees(x, P, chart, xt, slots.occupied[rows, k])
    for key, d in dof.items():
        nees_dof[key][rows, k] = d
    return _nees_array(v)


def _record_slot_nees(nees_all: Array, nees_dof: dict[str, Array], slots: sl.Schedule, rows: Array, k: int, x: Array,
                      P: Array, x_true: Array, chart: str) -> None:  # fmt: skip
    """``_record_nees`` with feature slots (``_slot_nees``)."""
    with np.errstate(all="ignore"):
        try:
            nees_all[rows, k] = _slot_nees(nees_dof, slots, rows, k, x, P, x_true, chart)
        except np.linalg.LinAlgError:
            pass


@dataclass(frozen=True)
class StepData:
    """What every trial of a chunk measured at one step (``_update`` makes the ``relnav.StepMeasurement``)."""

    y: Array  # (B, N, C) every feature's measurement
    alpha: Array  # (B, 3) measured angular acceleration (0 where not available)
    t: float
    alpha_var: Array | None  # (B, 3) per-trial R of the pseudo rows; None: the filter's sigma_alpha^2
    feature_var: Array | None = None  # (B, N, C) per-trial additions to the features' R; None: none


def _update(update, kernels: str, xa: Array, Pa: Array, active: Array, measured: StepData, visible: Array,
            kept: Array | None, k: int, x_true: Array, fs: FilterSetup, setup: Setup,
            as_one: bool = False):  # fmt: skip
    """``_robust_update`` of the priors ``xa, Pa`` of the trials ``active`` at step ``k``.

    Shared visibility ``(K+1, N)``: one update of them all. Per-trial visibility ``(B, K+1, N)`` (a
    dispersed target): one update per pattern of visible features among them, each trial's with exactly
    the features it sees (the same as the trial run alone, at the cost of its own features: a stack of
    the features any trial sees, masked per trial, costs that of the whole stack for every trial in the
    rows' Gram product), merged in ``active``'s order; or with ``as_one`` (``filters.compiled.masks_visibility``:
    the kernels' large-state update, where a masked row costs nothing in the system) one update of the union of
    their views, each trial's own view its row mask (``_update_as_one``: the same numbers, without a call and a
    gather per pattern). ``kernels == 'compiled'``: the update also evaluates the posteriors' NEES against
    ``x_true`` (``(n,)`` shared or ``(B, n)``), in cache.
    """
    if as_one and visible.ndim == 3:
        seen = visible[active, k]
        union = seen.any(axis=0)
        if not (seen == union).all():  # (one pattern: the loop below, one group)
            from ..filters.compiled import NotMaskable

            try:
                return _update_as_one(update, xa, Pa, active, measured, visible[:, k], union, kept, k, x_true, fs,
                                      setup)  # fmt: skip
            except NotMaskable:  # a trial for numpy's algebra: per pattern, each trial with exactly its features
                pass
    groups = [(visible[k], None)] if visible.ndim == 2 else _patterns(visible[active, k])
    parts = []
    for vis, j in groups:
        sel, rows = (slice(None), active) if j is None else (active[j], np.arange(j.size))
        step = relnav.StepMeasurement(
            y=relnav.stack_measurement(measured.y[sel], vis, setup.pseudo), alpha=measured.alpha[sel], visible=vis,
            t=measured.t, alpha_var=None if measured.alpha_var is None else measured.alpha_var[sel],
            feature_var=None if measured.feature_var is None else measured.feature_var[sel],
            feature_mask=None if kept is None else kept[sel, k][:, vis],
        )  # fmt: skip
        f = update
        if kernels == "compiled":
            f = functools.partial(update, x_true=x_true if x_true.ndim == 1 else x_true[sel])
        if j is None:
            return _robust_update(xa, Pa, step, rows, fs, setup, f)
        parts.append((j, *_robust_update(xa[j], Pa[j], step, rows, fs, setup, f)))
    return _merge(parts, active.size)


def _update_as_one(update, xa: Array, Pa: Array, active: Array, measured: StepData, seen: Array, union: Array,
                   kept: Array | None, k: int, x_true: Array, fs: FilterSetup, setup: Setup):  # fmt: skip
    """``_update`` of a dispersed batch as one update of the features any trial sees (``union (N,)``), each
    trial's own view (``seen (B, N)``) its ``offered`` rows (``relnav.StepMeasurement``) and, with the tracker's
    delivered features, its ``feature_mask``. The rows outside a trial's view measure ``y = 0`` (finite: they are
    taken out with ``h = y``, ``H = 0``). Raises ``filters.compiled.NotMaskable`` where the update cannot keep a
    trial to its own features."""
    offered = seen[:, union]
    y = relnav.stack_measurement(measured.y, union, setup.pseudo)
    F, C = offered.shape[1], measured.y.shape[-1]
    y[:, : F * C].reshape(-1, F, C)[~offered] = 0.0
    step = relnav.StepMeasurement(
        y=y, alpha=measured.alpha, visible=union, t=measured.t, alpha_var=measured.alpha_var,
        feature_var=measured.feature_var, feature_mask=offered if kept is None else kept[:, k][:, union] & offered,
        offered=offered,
    )  # fmt: skip
    return _robust_update(xa, Pa, step, active, fs, setup, functools.partial(update, x_true=x_true))


def _patterns(visible: Array) -> list[tuple[Array, Array]]:
    """``(pattern (N,), positions)`` of each distinct row of ``visible (b, N)``."""
    pats, inverse = np.unique(visible, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    return [(pats[c], np.flatnonzero(inverse == c)) for c in range(pats.shape[0])]


def axis_errors(x: Array, P: Array, x_true: Array, error_state: str = "attitude") -> tuple[Array, Array]:
    """Per-axis error and the filter's standard deviation of it ``(B, len(AXES))`` each, in ``AXIS_UNITS``.

    The error is ``eps`` of the attitude chart with ``x_hat = x_true [+] eps`` (``core.errorstate``: d rho,
    d rho_dot, d omega, the attitude error vector ``a``, d k), the quantities the block NEES are evaluated on;
    its covariance is ``M P M^T`` restricted to these rows, ``M`` mapping the filter's own error state (or the full
    state) to ``eps`` at ``x_hat``, as ``core.aligned.nees_report`` maps it. NaN where the state is not finite.
    """
    with np.errstate(all="ignore"):
        n = x.shape[-1]
        rows = np.r_[0 : es.ATT.stop, es.k_slice(st.n_points(n))]  # rho, rho_dot, omega, attitude come first; k last
        eps = es.estimation_error(x, x_true)[..., rows]
        if P.shape[-1] == n:  # the full state's covariance: eps = T dx
            M = es.error_map(x)[..., rows, :]
        elif error_state == "aligned":
            M = es.error_map(x)[..., rows, :] @ aligned.chart_jacobian(x)
        else:  # the attitude chart's own covariance
            M = None
        if M is None:
            var = np.diagonal(P, axis1=-2, axis2=-1)[..., rows]
        else:
            var = np.sum((M @ P) * M, axis=-1)  # diag(M P M^T) by one BLAS product
        return _in_axis_units(eps, var)


def axis_errors_of(x: Array, P: Array, x_true: Array, error_state: str = "attitude",
                   kernels: str = "numpy") -> tuple[Array, Array]:  # fmt: skip
    """``axis_errors`` on the ``kernels`` path: numpy, or the compiled ``core.kernels.axes.axis_errors`` (the same
    numbers to round-off: tests/core/test_kernels_axes.py)."""
    if kernels == "compiled":
        from ..core.kernels import axes

        return axes.axis_errors(x, P, x_true, error_state, _AXIS_SCALE)
    return axis_errors(x, P, x_true, error_state)


def _in_axis_units(eps: Array, var: Array) -> tuple[Array, Array]:
    """Per-axis errors ``eps`` and their variances ``var`` (SI) as ``(error, sigma)`` in ``AXIS_UNITS`` (a negative
    variance: NaN sigma)."""
    with np.errstate(invalid="ignore"):
        return eps * _AXIS_SCALE, np.sqrt(np.where(var >= 0, var, np.nan)) * _AXIS_SCALE


def _posterior_axes(u, x_true: Array, error_state: str, kernels: str) -> tuple[Array, Array]:
    """``axis_errors_of`` the update ``u``'s posteriors: those the compiled update gave beside their NEES (``u.axes``,
    the aligned chart's: the same numbers, unscaled), the others (the other charts, the trials numpy updated, those
    whose NEES were not evaluated) computed here."""
    raw = getattr(u, "axes", None)
    todo = None if raw is None else np.flatnonzero(np.isnan(raw[:, 0]))
    if raw is None or todo.size == raw.shape[0]:
        return axis_errors_of(u.x, u.P, x_true, error_state, kernels)
    n_ax = len(AXES)
    err, sig = _in_axis_units(raw[:, :n_ax], raw[:, n_ax:])
    if todo.size:
        xt = x_true if x_true.ndim == 1 else x_true[todo]
        err[todo], sig[todo] = axis_errors_of(u.x[todo], u.P[todo], xt, error_state, kernels)
    return err, sig


def _gated_out(gated: Array, dof: Array, channels: int, fraction: float) -> Array:
    """Per trial: at every step of the window, ``gated >= fraction`` of the features given (used + gated)."""
    used = (dof - dof % channels) // channels  # the pseudo rows (3 < channels) are the remainder
    offered = used + gated
    return np.all((offered > 0) & (gated >= fraction * offered), axis=-1)


def true_state(x_true: Array, k: int, rows: Array) -> Array:
    """The true state at step ``k`` of trials ``rows``: of the shared truth ``(K+1, n)`` or per trial ``(B, K+1, n)``."""
    return x_true[k] if x_true.ndim == 2 else x_true[rows, k]


def _omega_var(P: Array) -> Array:
    """Diagonal ``(B, 3)`` of the ``omega`` block of ``P (B, n, n)``."""
    return np.diagonal(P[:, st.OMEGA, st.OMEGA], axis1=-2, axis2=-1).copy()


KERNELS = ("numpy", "compiled")


def step_functions(kernels: str):
    """The module whose ``predict`` and ``update`` run the filter step: ``estimators`` (numpy) or ``compiled``."""
    if kernels == "numpy":
        return estimators
    if kernels == "compiled":
        from ..filters import compiled

        return compiled
    raise ValueError(f"unknown kernels {kernels!r} (expected one of {', '.join(KERNELS)})")


ALONE = 16  # _robust_update: up to this many trials left to numpy's update are updated one by one


def _robust_update(xa, Pa, step, rows, fs, setup, update=estimators.update, failed=None):
    """The batched update; if linear algebra fails for the batch, on halves of it down to single trials.

    Returns the update and, per trial, the failure reason ('' when it went through).
    A trial whose own update fails gets NaN state and covariance. Trials are independent
    in every kernel, so a trial's result does not depend on the sub-batch it ran in;
    bisection costs ``O(log B)`` extra calls per failing trial instead of ``B``.
    ``failed``: the message of the error ``update`` already raised on exactly this batch (it is
    split without a second try). Only the message is kept: the exception would hold its
    traceback's frames, the batch's arrays with them, in a reference cycle until the garbage
    collector's next pass (25 MB per 250-trial chunk of case B, measured).

    The few trials (2 to ``ALONE``) that the compiled update leaves to numpy's
    (``filters.compiled.PartialUpdateError``: numpy's has failed on them as a batch, or was not
    tried on them as one) are updated one by one: the same results as bisecting them, in ``k``
    calls instead of ~``2k - 2``.
    """
    if failed is None:
        try:
            return update(xa, Pa, step, rows, fs, setup), [""] * rows.size
        except np.linalg.LinAlgError as exc:
            if getattr(exc, "bad", None) is not None:  # filters.compiled.PartialUpdateError
                return _left_to_numpy(xa, Pa, step, rows, fs, setup, exc)
            failed = str(exc)
    if rows.size == 1:
        n, ne, m = xa.shape[-1], Pa.shape[-1], step.y.shape[-1]
        nan = relnav.GatedUpdate(np.full((1, n), np.nan), np.full((1, ne, ne), np.nan), np.full((1, m), np.nan),
                                 np.full(1, np.nan), np.zeros(1, int), np.zeros(1, bool), np.zeros(1, int),
                                 np.zeros(1, int))  # fmt: skip
        return nan, [f"linear algebra failure in the update: {failed}"]
    h = rows.size // 2
    (u1, r1), (u2, r2) = (_robust_update(xa[sl], Pa[sl], step, rows[sl], fs, setup, update)
                          for sl in (slice(0, h), slice(h, None)))  # fmt: skip
    return _concatenate([u1, u2]), r1 + r2


def _left_to_numpy(xa, Pa, step, rows, fs, setup, exc):
    """``_robust_update`` of a batch on which the compiled update went through but for the trials ``exc.bad``, left
    to numpy's update (``filters.compiled.PartialUpdateError``: it failed on them as one batch, or, for 2 to
    ``compiled.ONE_BY_ONE`` of them, was not tried): those trials alone, one by one (2 to ``ALONE``, or not tried:
    ``k`` calls of numpy's update, where a bisection makes ~``2k - 2``) or bisected without a second try, patched
    into the others' results ``exc.update``. Numpy's update here is ``filters.compiled.numpy_update``: its algebra and
    solvers on the compiled measurement model, as the compiled update's own fallback."""
    from ..filters.compiled import numpy_update, patch

    bad = exc.bad
    idx = np.flatnonzero(bad)
    if 1 < idx.size <= ALONE or not exc.tried:
        # copies ([i], not views): nothing that numpy's failure leaves behind holds the caller's arrays
        parts = [_robust_update(xa[[i]], Pa[[i]], step, rows[[i]], fs, setup, numpy_update)
                 for i in idx.tolist()]  # fmt: skip
        sub, why = _concatenate([p[0] for p in parts]), [r for p in parts for r in p[1]]
    else:
        sub, why = _robust_update(xa[bad], Pa[bad], step, rows[bad], fs, setup, numpy_update, str(exc))
    reasons = [""] * rows.size
    for i, r in zip(idx.tolist(), why):
        reasons[i] = r
    return patch(exc.update, bad, sub), reasons


# the compiled update's optional fields (relnav.GatedUpdate) and their shape in an update u that lacks them
_OPTIONAL = {"P_factor": lambda u: u.P.shape, "nees": lambda u: (u.P.shape[0], 8), "nees_pd": lambda u: u.P.shape[:1],
             "axes": lambda u: (u.P.shape[0], 2 * len(AXES))}  # fmt: skip


def _concatenate(updates: list):
    """The updates of consecutive parts of a batch as one (``_merge``)."""
    ends = np.cumsum([0] + [u.x.shape[0] for u in updates])
    return _merge([(np.arange(a, b), u, []) for a, b, u in zip(ends, ends[1:], updates)], int(ends[-1]))[0]


def _merge(parts: list, b: int):
    """``(update, reasons)`` of a batch of ``b`` trials from ``(positions, update, reasons)`` of its parts.

    MEKF/UKF updates carry no gate counts: the fields all parts have. ``P_factor``, ``nees``, ``nees_pd`` and ``axes``
    (given by the compiled update only) are NaN for the parts without them, None if no part has them. The
    innovations ``nu`` of parts with fewer rows are padded with NaN."""
    updates = [u for _, u, _ in parts]
    cls = relnav.GatedUpdate if all(isinstance(u, relnav.GatedUpdate) for u in updates) else kf.Update
    out = {}
    for f in dataclasses.fields(cls):
        vals = [getattr(u, f.name) for u in updates]
        if f.name in _OPTIONAL:
            if all(v is None for v in vals):
                out[f.name] = None
                continue
            vals = [np.full(_OPTIONAL[f.name](u), np.nan) if v is None else v for u, v in zip(updates, vals)]
        tail = tuple(max(d) for d in zip(*(v.shape[1:] for v in vals)))
        if all(v.shape[1:] == tail for v in vals):
            a = np.empty((b,) + tail, np.result_type(*vals))
        else:
            a = np.full((b,) + tail, np.nan)
        for (j, _, _), v in zip(parts, vals):
            a[(j,) + tuple(slice(0, d) for d in v.shape[1:])] = v
        out[f.name] = a
    reasons = [""] * b
    for j, _, why in parts:
        for i, r in zip(j.tolist(), why):
            reasons[i] = r
    return cls(**out), reasons


def nees_of(x: Array, P: Array, x_true: Array, error_state: str = "attitude", kernels: str = "numpy") -> dict[str, Array]:
    """Full, block and gauge-projected NEES (docs/filters.md) of estimates ``(x, P)``.

    Full and gauge-projected NEES in the aligned chart, blocks in the attitude chart
    (``core.aligned.nees_report``).

    ``P`` is the covariance of the full state ``(B, n, n)`` (mapped to the error state at
    the estimate) or of the filter's error state ``(B, n-1, n-1)``: the attitude chart's
    (MEKF, UKF), or the aligned chart's (``error_state: aligned``, mapped to the attitude
    chart, in which every NEES is reported).
    """
    return nees_and_pd(x, P, x_true, error_state, kernels)[0]


def aligned_covariance(x: Array, P: Array, error_state: str = "attitude") -> Array:
    """A filter's covariance ``P`` at ``x`` as that of the aligned error state (``core.aligned``)."""
    if P.shape[-1] == x.shape[-1]:
        T = aligned.error_map(x)
        return T @ P @ np.swapaxes(T, -1, -2)
    if error_state == "aligned":
        return P
    return aligned.from_attitude_chart(x, P)


def attitude_covariance(x: Array, P: Array, error_state: str = "attitude") -> Array:
    """A filter's covariance ``P`` at ``x`` as that of the attitude-chart error state (``core.errorstate``)."""
    if P.shape[-1] == x.shape[-1]:
        return es.to_error_covariance(x, P)
    if error_state == "aligned":
        return aligned.to_attitude_chart(x, P)
    return P


def nees_and_pd(x: Array, P: Array, x_true: Array, error_state: str = "attitude", kernels: str = "numpy",
                P_factor: Array | None = None) -> tuple[dict[str, Array], Array | None]:  # fmt: skip
    """``nees_of`` and, from the compiled kernel, whether ``P`` is positive definite.

    The second item is None where the numpy path computed the NEES (``_check`` then factorizes ``P``).
    ``P_factor``: square roots of ``P`` as the compiled update gives them (``GatedUpdate.P_factor``), used by the
    compiled kernel instead of factorizing ``P`` again.
    """
    if kernels == "compiled":
        from ..core.kernels import consistency  # the same numbers to round-off (tests/core/test_kernels_consistency.py)

        attitude = P.shape[-1] != x.shape[-1] and error_state != "aligned"  # aligned_covariance's cases
        return consistency.nees_and_pd(x, P, x_true, attitude, P_factor)
    with np.errstate(all="ignore"):
        return aligned.nees_report(x, aligned_covariance(x, P, error_state), x_true), None


def _posterior_nees(u, x_true: Array, error_state: str, kernels: str) -> tuple[Array, Array | None]:
    """``nees_and_pd`` of the update ``u``'s posteriors as one array ``(B, 8)`` in ``_nees_keys``' order: those the
    compiled update evaluated (``u.nees``), the others (the trials numpy updated, or every trial when none was
    evaluated) computed here."""
    ev, epd = getattr(u, "nees", None), getattr(u, "nees_pd", None)
    if ev is None:
        v, pd = nees_and_pd(u.x, u.P, x_true, error_state, kernels, getattr(u, "P_factor", None))
        return _nees_array(v), pd
    todo = np.isnan(epd)
    pd = epd == 1.0
    if todo.any():
        ev = ev.copy()
        rest = np.flatnonzero(todo)
        xt = x_true if x_true.ndim == 1 else x_true[rest]
        v, p = nees_and_pd(u.x[rest], u.P[rest], xt, error_state, kernels,
                           None if u.P_factor is None else u.P_factor[rest])  # fmt: skip
        ev[rest] = _nees_array(v)
        pd[rest] = p
    return ev, pd


def _nees_keys() -> tuple[str, ...]:
    """The NEES of ``GatedUpdate.nees``, in its column order (``core.kernels.consistency.KEYS``)."""
    from ..core.kernels.consistency import KEYS

    return KEYS


def _nees_array(v: dict[str, Array]) -> Array:
    """``nees_of``'s dict as an array ``(B, 8)`` in ``_nees_keys``' order."""
    return np.stack([v[k] for k in _nees_keys()], axis=-1)


def _record_nees(nees_all: Array, rows: Array, k: int, x: Array, P: Array, x_true: Array,
                 error_state: str = "attitude", kernels: str = "numpy") -> None:  # fmt: skip
    """``nees_all[rows, k]``: the NEES of ``(x, P)`` (left NaN where linear algebra fails)."""
    with np.errstate(all="ignore"):
        try:
            nees_all[rows, k] = _nees_array(nees_of(x, P, x_true, error_state, kernels))
        except np.linalg.LinAlgError:
            pass


@dataclass
class ChunkResult:
    trials: Array  # (B,) trial indices
    runs: list[FilterRun]
    runtime_s: float
    faults: Faults | None = None  # the trials' tracker faults (None: an ideal tracker)


def run_chunk(seed: int, trials: Array, setup: Setup, truth: Truth, exact: meas.Measurements,
              filters: list[FilterSetup], bounds: Bounds, kernels: str = "numpy",
              tick: Callable[[int], None] | None = None) -> ChunkResult:  # fmt: skip
    """Draw the chunk's trials and run every filter on the same draws (``tick``: ``run_filter``'s)."""
    t0 = time.perf_counter()
    draws = meas.draw_trials(seed, trials, setup.x0.size, setup.steps, setup.n_points)
    noisy = meas.noisy(setup, exact, draws)
    x0_hat = meas.initial_estimates(setup, draws)
    P0 = None
    if setup.initial_estimate == "measurements":
        x0_hat, P0 = measurement_start(setup, filters[0], noisy.y[:, 0], exact.visible[0], x0_hat)
    y, faults = noisy.y, None
    if setup.sensor.faults:
        y, faults = apply_faults(setup.sensor, seed, trials, noisy.y, exact.y, exact.visible)
    runs = []
    for fs in filters:
        t1 = time.perf_counter()
        r = run_filter(x0_hat, setup, truth, y, noisy.alpha, exact.visible, fs, bounds,
                       None if faults is None else faults.kept, P0, kernels, tick)  # fmt: skip
        r.runtime_s = np.full(len(trials), (time.perf_counter() - t1) / len(trials))
        runs.append(r)
    return ChunkResult(np.asarray(trials), runs, time.perf_counter() - t0, faults)
