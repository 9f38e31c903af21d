"""Unscented filter of the relative-navigation problem with a multiplicative attitude.

Sigma points live on the error state of ``core.errorstate`` (``n - 1`` dimensions, the
attitude as a 3-vector, ``x [+] eps`` the chart), as in Crassidis & Markley's USQUE; the
kernels are ``core.unscented``. Each sigma point is propagated by the same RK4 as the
other filters; ``Q`` is the scenario's block Q mapped to the error state
(``filters/mekf.error_process_noise``); the measurement model is the stacked stereo and
pseudo-measurement model of ``filters/relnav``. Scaling ``alpha, beta, kappa`` per filter
entry.
"""

from __future__ import annotations

import numpy as np

from ..config.filters import UKFSetup
from ..config.resolve import Setup
from ..core import dynamics
from ..core import kalman as kf
from ..core import unscented as ut
from . import gating, mekf, relnav
from .mekf import error_process_noise


def predict(x, P, t, fs: UKFSetup, setup: Setup, propagate=None, charts=None):
    """``(x-, P-)`` with ``P`` the error-state covariance.

    ``propagate(states (M, n))``: the RK4 of the step with the quaternion renormalized, for
    any number of states (default: ``dynamics.propagate``; ``filters.compiled`` passes its
    compiled twin). ``charts``: ``(chart, local)`` of the error state, batched over any leading
    axes (default: those of ``mekf.chart_of(fs)``; ``filters.compiled`` passes compiled twins).
    """
    if propagate is None:

        def propagate(states):
            return relnav.renormalize(dynamics.propagate(states, t, setup.dt, setup.orbit, fs.substeps))

    def f(states, _idx):
        return propagate(states)

    # Q is mapped at the propagated centre point (the mean's chart differs from it by the mean increment)
    x_c = propagate(x)
    ch = mekf.chart_of(fs)
    chart, local = charts or (ch.chart, ch.local)
    return ut.predict(x, P, f, error_process_noise(x_c, fs.Q_diag, ch), fs.alpha, fs.beta, fs.kappa,
                      chart=chart, local=local)  # fmt: skip


def update(x, P, step: relnav.StepMeasurement, rows, fs: UKFSetup, setup: Setup, measure_h=None,
           charts=None) -> kf.Update:  # fmt: skip
    """The unscented update (or, at an iterated first update, the error-state filter's iterated one).

    The features the tracker did not deliver (``step.feature_mask``) are taken out of the
    update, as in the other filters; the UKF has no gate (the scenario rejects ``gating``).

    ``measure_h(states (M, n), trials (M,))``: the stacked ``h`` of the step at each state, with
    the pseudo rows of the state's trial (index into the step's batch); default
    ``relnav.measurement_model``, ``filters.compiled`` passes its compiled twin; ``charts`` as in
    ``predict`` (only the chart is used).
    """
    if relnav.iterated_at(fs, setup, step):  # first_update: iterated, the error-state filter's iterated update
        return mekf.update(x, P, step, rows, fs, setup)
    R = relnav.measurement_noise(fs, setup, int(step.visible.sum()), None if step.alpha_var is None else step.alpha_var[rows])
    if measure_h is None:
        measure = relnav.measurement_model(setup, step)

        def measure_h(states, trials):
            return measure(states, trials, jac=False)[0]

    def model(states, trials, jac=False):
        return measure_h(states, trials), None

    B = x.shape[0]
    used = np.full(B, int(step.visible.sum()))
    if step.feature_mask is not None:  # the features the tracker did not deliver: h = y on their rows at every sigma
        # point (gating.masked_measure, as for the other filters), so they add nothing to y_bar, S, C or the NIS
        keep = step.feature_mask[rows]
        model = gating.masked_measure(model, step.y, rows, keep, relnav.channel_variances(fs, setup.disparity).size)
        used = keep.sum(axis=-1)

    def h(states, idx):
        return model(states, rows[idx], False)[0]

    chart = charts[0] if charts else mekf.chart_of(fs).chart
    x_new, P_new, nu, nis = ut.update(x, P, step.y[rows], h, R, fs.alpha, fs.beta, fs.kappa, chart=chart)
    return relnav.GatedUpdate(x_new, P_new, nu, nis, np.ones(B, int), np.ones(B, bool), np.zeros(B, int), used)
