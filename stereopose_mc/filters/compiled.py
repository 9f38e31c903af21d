"""The filter step of ``filters.relnav`` on the compiled kernels (``--kernels compiled``).

Same functions, same arguments, same results (to round-off) as ``relnav.predict`` and
``relnav.update``; ``relnav`` stays the readable reference. What changes is where the
work is done:

- prediction: ``F`` only on its non-zero block, ``Phi`` by Taylor/Horner on that
  15-column block (``expm`` when the scenario asks for it, on the same block), RK4 fused
  per trial, ``P- = Phi P Phi^T + Q`` block-structured (``core.kernels.model``);
- measurement: ``h`` and the row-sparse ``H`` per feature in one compiled pass; the
  update fused with the measurement model, per trial, on the row-sparse ``H``
  (``core.kernels.update``): EKF, and IEKF with line search, Levenberg-Marquardt or plain
  Gauss-Newton steps; the gate's distances come from the compiled ``h``/``H`` and the
  numpy gating functions; given the truth (``x_true``, the engine's runs), the update kernels
  evaluate each posterior's NEES too (``GatedUpdate.nees``); a trial whose factorization
  fails is updated by numpy's filter algebra on the compiled measurement model
  (``numpy_update``).

Filters with an error state (``filters/mekf.py`` is their reference) run the same kernels
in its chart: the aligned one (``error_state: aligned``, the default of the EKF, IEKF and
MEKF; ``core.kernels.aligned``) or the attitude one (``error_state: attitude``, the
multiplicative EKF; ``core.kernels.attitude``): ``P- = Phi_e P Phi_e^T + T Q T^T`` with
``Phi_e = T(x-) Phi S(x+)``, and the updates on the row-sparse ``H_e = H S`` with the reset
``x+ = x- [+] e+`` (the EKF's iterated first update included). The UKF (``filters/ukf.py``)
propagates and measures its sigma points with the compiled RK4 and ``h`` (``_propagator``,
``_measurer``) and maps them with the compiled charts (``_charts``: ``x [+] e`` and its inverse);
its unscented algebra stays numpy (batched BLAS products, ``core.unscented``); its iterated first
update (``first_update: iterated``, the error-state IEKF's) runs the update kernels.
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import NDArray

from ..config.resolve import FilterSetup, Setup
from ..core.kernels import aligned as ka
from ..core.kernels import charts as kch
from ..core.kernels import gate as kg
from ..core.kernels import model as km
from ..core.kernels import secondorder as kso
from ..core.kernels import update as ku
from ..core.kernels import writable as _writable
from ..core.kernels.whiten import LARGE_N
from ..core.layout import (CHART_ALIGNED, CHART_ATTITUDE, CHART_FULL, CHARTS, E_POINTS, POINTS, n_channels,
                           n_measurements)
from ..core.orbit import leader_kinematics
from . import estimators, registry, relnav, ukf

Array = NDArray[np.float64]
CHART_CODES = CHARTS  # the kernels' ``chart`` argument (core.layout)
_CONSTANTS: dict = {}  # per-configuration arrays of the step (_constants, _q_batch)
# 2 to this many trials the kernels leave to numpy's update (their P- or A does not factorize) are handed to the
# caller (PartialUpdateError, tried=False), which updates them one by one (mc.trial._left_to_numpy) with no batch
# attempt first: such trials are diverging, and a batch attempt that fails on one of them is a call spent for nothing
# (in case B's full-state EKF every one failed: 8 numpy calls per run instead of 10)
ONE_BY_ONE = 16


def chart_code(fs: FilterSetup) -> int | None:
    """The kernels' ``chart`` of a filter (its registry entry's chart): 0 the full state, 1 the aligned error state,
    2 the attitude error state, None: its type has no compiled step."""
    if registry.of(fs).compiled is None:
        return None
    return CHART_CODES[registry.chart(fs)]


@functools.lru_cache(maxsize=4096)
def _leader(orbit, t: float, h: float = 0.0, stages: int = 1) -> tuple[Array, Array, Array]:
    """``(r_L, nu', nu'')`` at ``t + i h / 2``, ``i < stages``: the same for every trial, chunk and filter of a
    step, so computed once (``leader_kinematics`` is a Kepler solve in numpy on a few scalars)."""
    lk = leader_kinematics(orbit, t + 0.5 * h * np.arange(stages))
    return tuple(np.ascontiguousarray(v, dtype=float) for v in (lk.r, lk.nu_dot, lk.nu_ddot))


def _q_batch(Q: Array, B: int, n: int) -> Array:
    """``Q (n,)`` repeated for ``B`` trials (kept per ``Q`` and ``B``: the kernels do not write it)."""
    key = (id(Q), B, n)
    hit = _CONSTANTS.get(key)
    if hit is not None and hit[0] is Q:
        return hit[2]
    out = _writable(np.broadcast_to(np.asarray(Q, dtype=float), (B, n)))
    _CONSTANTS[key] = (Q, None, out)
    return out


def transition_block(x: Array, t: float, fs: FilterSetup, setup: Setup, lk=None) -> Array:
    """``Phi[:, 0:13, c]`` (``B, 13, 15``) at the posterior ``x`` (the rest of ``Phi`` is the identity).

    ``lk``: the leader's ``(r, nu_dot, nu_ddot)`` at ``t`` when the caller has them.
    """
    if lk is None:
        lk = tuple(float(v[0]) for v in _leader(setup.orbit, float(t)))
    Fr = km.F_reduced_batch(x, lk[0], lk[1], lk[2], setup.orbit.mu)
    if fs.transition == "expm":
        from scipy.linalg import expm

        A = np.zeros(Fr.shape[:-2] + (15, 15))
        A[:, :13] = Fr * setup.dt
        return np.ascontiguousarray(expm(A)[:, :13])
    return km.transition_reduced_batch(Fr, setup.dt, fs.taylor_order)


def predict(x: Array, P: Array, t: float, fs: FilterSetup, setup: Setup) -> tuple[Array, Array]:
    """``(x-, P-)`` at ``t + dt`` by the compiled step of ``fs``'s type (``registry.steps``; numpy's without one)."""
    return registry.steps(fs, "compiled").predict(x, P, t, fs, setup)


def ukf_predict(x: Array, P: Array, t: float, fs: FilterSetup, setup: Setup) -> tuple[Array, Array]:
    """The UKF's prediction, its sigma points through the compiled RK4 and chart."""
    return ukf.predict(x, P, t, fs, setup, propagate=_propagator(t, fs, setup), charts=_charts(fs))


def kernel_predict(x: Array, P: Array, t: float, fs: FilterSetup, setup: Setup) -> tuple[Array, Array]:
    """``(x-, P-)`` at ``t + dt`` from the posterior ``(x, P)`` at ``t`` (``relnav.predict``, ``mekf.predict``)."""
    chart = chart_code(fs)
    x, P = _writable(x), _writable(P)
    B, n = x.shape
    h = setup.dt / fs.substeps
    # the leader once for all the RK4 stage times; the first is t, where F is evaluated
    r, nd, ndd = _leader(setup.orbit, float(t), h, 2 * fs.substeps + 1)
    if fs.transition == "expm":
        T = transition_block(x, t, fs, setup, (float(r[0]), float(nd[0]), float(ndd[0])))
        x_pred = km.propagate_batch(x, r, nd, ndd, h, setup.orbit.mu, fs.substeps, True)
    else:  # the same kernels in one call
        x_pred, T = km.predict_state_batch(x, r, nd, ndd, h, setup.orbit.mu, fs.substeps, setup.dt, fs.taylor_order)
    Q = process_noise(x, P, t, fs, setup, float(nd[0]))
    if chart != CHART_FULL:
        return x_pred, ka.predict_covariance_batch(x, x_pred, T, P, Q, chart)
    return x_pred, km.predict_covariance_batch(P, T, Q)


def process_noise(x: Array, P: Array, t: float, fs: FilterSetup, setup: Setup, nd: float | None = None) -> Array:
    """``relnav.process_noise`` as ``(B, n)`` on the compiled kernel (``secondorder.rate_noise_batch``); ``nd``: the
    leader's ``nu'`` at ``t`` when the caller has it."""
    B, n = x.shape
    if not fs.second_order:
        return _q_batch(fs.Q_diag, B, n)
    if nd is None:
        nd = float(_leader(setup.orbit, float(t))[1][0])
    x, P = _writable(x), _writable(P)
    return kso.rate_noise_batch(x, P, relnav.omega_rows(x, P).start, nd, float(setup.dt), fs.Q_diag)


def _propagator(t: float, fs: FilterSetup, setup: Setup):
    """``states (M, n) -> x(t + dt)``: the filter's RK4 with the quaternion renormalized, compiled
    (``model.propagate_batch``; ``relnav.renormalize(dynamics.propagate(...))`` in numpy)."""
    h = setup.dt / fs.substeps
    r, nd, ndd = _leader(setup.orbit, float(t), h, 2 * fs.substeps + 1)

    def propagate(states: Array) -> Array:
        return km.propagate_batch(_writable(states), r, nd, ndd, h, setup.orbit.mu, fs.substeps, True)

    return propagate


def _batched(kernel):
    """``kernel(a (B, k), b (B, l))`` over any common leading axes of ``a`` and ``b`` (broadcast), like the numpy
    charts: flattened to one batch axis, contiguous, and shaped back."""

    def f(a: Array, b: Array) -> Array:
        lead = np.broadcast_shapes(a.shape[:-1], b.shape[:-1])
        a2 = np.ascontiguousarray(np.broadcast_to(a, lead + a.shape[-1:]), dtype=float).reshape(-1, a.shape[-1])
        b2 = np.ascontiguousarray(np.broadcast_to(b, lead + b.shape[-1:]), dtype=float).reshape(-1, b.shape[-1])
        out = kernel(a2, b2)
        return out.reshape(lead + out.shape[-1:])

    return f


def _charts(fs: FilterSetup) -> tuple:
    """``(chart, local)`` of a UKF's error state on the compiled kernels (``aligned`` or ``attitude``), as
    ``mekf.chart_of(fs)``'s numpy ones."""
    code = chart_code(fs)  # mekf.chart_of: the attitude chart for anything but "aligned"
    return (_batched(functools.partial(kch.chart_batch, code)), _batched(functools.partial(kch.local_batch, code)))


def flow_linearization_variance(x: Array, P: Array, setup: Setup) -> Array:
    """``relnav.flow_linearization_variance`` on the compiled kernel (``secondorder.flow_variance_batch``)."""
    x, P = _writable(x), _writable(P)
    w0 = relnav.omega_rows(x, P).start
    p0 = POINTS if P.shape[-1] == x.shape[-1] else E_POINTS
    return kso.flow_variance_batch(x, P, w0, p0, float(setup.baseline), bool(setup.disparity), float(setup.focal))


def pseudo_linearization_variance(x: Array, P: Array, setup: Setup, t: float) -> Array:
    """``relnav.pseudo_linearization_variance`` on the compiled kernel (``secondorder.pseudo_variance_batch``)."""
    x, P = _writable(x), _writable(P)
    _, nd, _ = _leader(setup.orbit, float(t))
    return kso.pseudo_variance_batch(x, P, relnav.omega_rows(x, P).start, float(nd[0]))


def step_model(setup: Setup, vis: Array, nd: float, ndd: float) -> km.StepModel:
    """The kernels' measurement model of a step (``model.StepModel``): the visible features ``vis`` (int64), the
    scenario's camera and pseudo rows, the leader's ``nu'``, ``nu''``; each field of the one type the kernels are
    compiled for (a float where an int was given would be a second signature of every kernel it enters)."""
    return km.StepModel(vis, float(setup.baseline), bool(setup.disparity), float(setup.focal), bool(setup.pseudo),
                        float(nd), float(ndd))  # fmt: skip


def _measurer(setup: Setup, step: relnav.StepMeasurement):
    """``(states (M, n), trials (M,)) -> h (M, m)``: ``relnav.measurement_model``'s ``h`` without ``H``, compiled
    (``model.measure_h_batch``), the pseudo rows with each state's trial's measured acceleration."""
    _, nd, ndd = _leader(setup.orbit, float(step.t))
    nd, ndd = float(nd[0]), float(ndd[0])
    model = step_model(setup, np.flatnonzero(step.visible).astype(np.int64), nd, ndd)

    def measure_h(states: Array, trials: Array) -> Array:
        alpha = _writable(step.alpha[trials]) if setup.pseudo else np.zeros((states.shape[0], 3))
        return km.measure_h_batch(_writable(states), model, alpha)

    return measure_h


def measurement_model(setup: Setup, step: relnav.StepMeasurement):
    """``relnav.measurement_model`` on the compiled model (``model.measure_batch``, ``H`` made dense): the same
    ``measure(x, rows, jac)``, the same ``h`` and ``H`` to round-off (1e-13 relative), without numpy's fixed cost
    per call, which dominates an update of a few trials."""
    _, nd, ndd = _leader(setup.orbit, float(step.t))
    nd, ndd = float(nd[0]), float(ndd[0])
    model = step_model(setup, np.flatnonzero(step.visible).astype(np.int64), nd, ndd)
    vis, C = tuple(model.vis.tolist()), n_channels(setup.disparity)

    def measure(x: Array, rows: Array, jac: bool = True):
        x = _writable(x)
        alpha = _writable(step.alpha[rows]) if setup.pseudo else np.zeros((x.shape[0], 3))
        if not jac:
            return km.measure_h_batch(x, model, alpha), None
        hx, Hval = km.measure_batch(x, model, alpha, True)
        n = x.shape[1]
        return hx, km.dense(Hval, _model_columns(n, vis, C, setup.pseudo), n)

    return measure


@functools.lru_cache(maxsize=256)
def _model_columns(n: int, vis: tuple, C: int, pseudo: bool) -> Array:
    """``model.measurement_columns`` kept per state size and visible features (never written)."""
    out = km.measurement_columns(n, np.array(vis, dtype=np.int64), C, pseudo)
    out.flags.writeable = False
    return out


def numpy_update(x: Array, P: Array, step: relnav.StepMeasurement, rows: Array, fs: FilterSetup, setup: Setup):
    """``estimators.update`` (numpy's filter algebra and solvers, their errors) on the compiled measurement model
    (``measurement_model``): the update of the trials the kernels leave to numpy (``compiled_update``,
    ``mc.trial._left_to_numpy``)."""
    return estimators.update(x, P, step, rows, fs, setup, model=measurement_model)


def gate_distances(x: Array, P: Array, y: Array, R: Array, alpha: Array, model: km.StepModel, cols: Array,
                   chart: int, nvis: int, C: int, offered: Array | None = None) -> Array:
    """The gate's squared distances ``d_f^2 = nu_f^T S_f^-1 nu_f`` ``(b, F)`` at the prior in the filter's coordinates,
    ``S_f = H_f P H_f^T + R_f`` from the row-sparse ``H`` (``core.kernels.gate``: the twin of ``gating.distances2``
    on ``gating.linearized_blocks`` of the dense ``H``, which costs ``C n^2`` per feature where this costs
    ``C 16^2``). A trial with a block that is not positive definite (a NaN ``d^2`` from the kernel's Cholesky
    factor) takes ``gating.distances2`` on its blocks, as every trial did before the kernel (``LinAlgError`` on a
    singular block, for ``mc.trial._robust_update``).

    ``chart`` 0: ``relnav.measurement_model`` at ``x``; 1, 2: ``mekf.error_measurement`` at ``e = 0``.
    ``offered (b, F)``: the features in each trial's own view (``relnav.StepMeasurement.offered``; None: all): only
    theirs are evaluated and checked, and a block to redo raises ``NotMaskable`` (LU on a trial's blocks would meet
    the others').
    """
    if chart == CHART_FULL:
        hx, Hval = km.measure_batch(x, model, alpha, True)
    else:
        hx, Hval = kch.measure_batch(chart, x, np.zeros(P.shape[:2]), model, alpha, True)
    nu = y - hx
    S, d2 = kg.innovation_blocks_batch(Hval, cols, P, R, nu, nvis, C, chart == CHART_ALIGNED,
                                       _all_offered(nvis) if offered is None else np.ascontiguousarray(offered, bool))
    nan = np.isnan(d2)
    redo = np.flatnonzero((nan if offered is None else nan & offered).any(axis=-1))
    if redo.size:
        if offered is not None:
            raise NotMaskable("a gate block of the batch is not positive definite")
        from . import gating

        d2[redo] = gating.distances2(nu[redo], S[redo])
    return d2


def _iterated(fs: FilterSetup, setup: Setup, step: relnav.StepMeasurement) -> dict | None:
    """The iterated update's knobs at this step (``relnav.kalman_update``), or None for the EKF update."""
    it = fs.iteration(relnav.first_update(setup, step))
    if it is None:
        return None
    return dict(tol=it.tolerance, max_iter=it.max_iterations, control=it.step_control, stopping=it.stopping)


def update(x: Array, P: Array, step: relnav.StepMeasurement, rows: Array, fs: FilterSetup, setup: Setup,
           x_true: Array | None = None):  # fmt: skip
    """The measurement update of ``estimators.update`` by the compiled step of ``fs``'s type (``registry.steps``).

    ``x_true``: the true states of the step's whole batch ``(B, n)`` (or one ``(n,)`` shared by all), indexed by
    ``rows`` as ``step.y``: the compiled update then evaluates each posterior's NEES (``GatedUpdate.nees``, the
    engine's consistency record: ``mc.trial``); None, or a filter without kernels: not evaluated here."""
    return registry.steps(fs, "compiled").update(x, P, step, rows, fs, setup, x_true=x_true)


def ukf_update(x: Array, P: Array, step: relnav.StepMeasurement, rows: Array, fs: FilterSetup, setup: Setup,
               x_true: Array | None = None):  # fmt: skip
    """The UKF's update, its sigma points through the compiled ``h`` and chart; its iterated first update on the
    update kernels (``kernel_update``)."""
    if relnav.iterated_at(fs, setup, step):
        return kernel_update(x, P, step, rows, fs, setup, x_true)
    return ukf.update(x, P, step, rows, fs, setup, measure_h=_measurer(setup, step), charts=_charts(fs))


def kernel_update(x: Array, P: Array, step: relnav.StepMeasurement, rows: Array, fs: FilterSetup, setup: Setup,
                  x_true: Array | None = None):  # fmt: skip
    """The update on the kernels of ``core.kernels.update`` where ``supported``, else numpy's (``x_true`` as in
    ``update``)."""
    hit = _CONSTANTS.get(("supported", id(fs)))
    if hit is None or hit[0] is not fs:
        hit = _CONSTANTS[("supported", id(fs))] = (fs, None, supported(fs))
    if not hit[2]:
        return estimators.update(x, P, step, rows, fs, setup)  # a filter type or option without kernels
    return compiled_update(x, P, step, rows, fs, setup, x_true)


@functools.lru_cache(maxsize=64)
def _all_offered(F: int) -> Array:
    """``(0, F)``: every feature offered to the gate's kernel (``core.kernels.gate``; never written)."""
    return np.empty((0, F), bool)


@functools.lru_cache(maxsize=16)
def _no_truth(n: int) -> Array:
    """``(0, n)``: no true states for the update kernels (nothing evaluated; never written)."""
    return np.empty((0, n))


def _row_mask(keep: Array | None, b: int, m: int, C: int) -> Array:
    """``(b, m)`` rows that enter the update: the kept features' channels and the pseudo rows."""
    mask = np.ones((b, m), bool)
    if keep is not None:
        mask[:, : keep.shape[-1] * C] = np.repeat(keep, C, axis=-1)
    return mask


def _constants(fs: FilterSetup, setup: Setup, visible: Array, b: int, ne: int) -> tuple:
    """``(vis, C, m, R (b, m), cols, mask of ones (b, m), zeros (b, 3), fixed)`` for this filter, visibility and
    batch size; ``fixed``: the update's per-trial fields that do not depend on the step when no feature is
    masked, ``(rejected 0, used nvis, iterations 1, converged True)`` of the EKF update, read-only.

    The same at every step where the same features are visible: kept (a few entries per
    run) so that a step does not rebuild them. ``R`` carries the filter's own pseudo-row
    variance (``compiled_update`` builds it per trial when the step brings ``alpha_var``).
    Shared between steps: the kernels never write their inputs, and ``fixed`` cannot be written.
    """
    key = (id(fs), id(setup), visible.tobytes(), b, ne)
    hit = _CONSTANTS.get(key)
    if hit is not None and hit[0] is fs and hit[1] is setup:
        return hit[2]
    vis = np.flatnonzero(visible).astype(np.int64)
    C = n_channels(setup.disparity)
    m = n_measurements(vis.size, setup.disparity, setup.pseudo)
    R = _writable(np.broadcast_to(relnav.measurement_noise(fs, setup, vis.size), (b, m)))
    chart = chart_code(fs)
    cols = (km.measurement_columns(ne, vis, C, setup.pseudo) if chart == CHART_FULL else
            kch.measurement_columns(chart, ne, vis, C, setup.pseudo))  # fmt: skip
    FC = vis.size * C  # the gate's kernel reads each feature's columns from its first row (core.kernels.gate)
    if not np.array_equal(cols[:FC], np.repeat(cols[:FC:C], C, axis=0)):
        raise ValueError("each feature's rows of the row-sparse H must see the same columns")
    fixed = (np.zeros(b, int), np.full(b, vis.size, np.int64), np.ones(b, int), np.ones(b, bool))
    for a in fixed:
        a.flags.writeable = False
    out = (vis, C, m, R, cols, np.ones((b, m), bool), np.zeros((b, 3)), fixed)
    if len(_CONSTANTS) > 64:  # a perturbed truth or a pseudo-row warm-up makes a new setup per step: bounded
        _CONSTANTS.clear()
    _CONSTANTS[key] = (fs, setup, out)  # the objects themselves: an id is never reused while they are held
    return out


def compiled_update(x: Array, P: Array, step: relnav.StepMeasurement, rows: Array, fs: FilterSetup, setup: Setup,
                    x_true: Array | None = None):  # fmt: skip
    """``estimators.update`` (EKF or IEKF, gating, fault masks) on the fused kernels of ``core.kernels.update``.

    The EKF or the IEKF as ``relnav.kalman_update`` chooses (``_iterated``). A trial whose
    Cholesky factorization fails (``S`` or ``P-`` not numerically positive definite, as in a
    filter that is losing track) is updated by ``estimators.update`` on the compiled measurement
    model (``numpy_update``), so it meets numpy's solvers and their errors as with ``--kernels
    numpy`` (on ``h`` and ``H`` equal to round-off): here for one such trial, or
    for more than ``ONE_BY_ONE`` as a batch; 2 to ``ONE_BY_ONE`` of them raise
    ``PartialUpdateError`` (``tried=False``) for the caller (``mc.trial._robust_update``) to update
    one by one, as it does when numpy's update fails on the batch. ``x_true`` as in ``update`` (the trials numpy
    updates have NaN ``nees``: not evaluated).

    ``step.offered`` (a dispersed batch as one update, ``masks_visibility``): the features out of a trial's view are
    rows out of its update (with ``feature_mask``, as a tracker's dropped features), which changes none of its
    numbers; where numpy's algebra would take over a trial (above) or the gate's (``gate_distances``), the update
    raises ``NotMaskable`` instead, for the caller to update the step per pattern of visible features.
    """
    chart, iterated = chart_code(fs), _iterated(fs, setup, step)
    x, P = _writable(x), _writable(P)
    b, ne = P.shape[:2]
    _, nd, ndd = _leader(setup.orbit, float(step.t))
    nd, ndd = float(nd[0]), float(ndd[0])
    vis, C, m, R, cols, ones, zeros3, (rejected, used, one_iteration, converged) = _constants(fs, setup, step.visible,
                                                                                              b, ne)  # fmt: skip
    nvis = vis.size
    # rows: increasing trial indices into the step's batch (mc.trial's active set); all of them: no gather
    every = rows.size == step.y.shape[0] and rows.size > 0 and rows[0] == 0 and rows[-1] == rows.size - 1
    y = _writable(step.y if every else step.y[rows])
    if (step.alpha_var is not None and setup.pseudo) or step.feature_var is not None:  # per-trial R rows
        av = step.alpha_var[rows] if step.alpha_var is not None and setup.pseudo else None
        fv = None if step.feature_var is None else step.feature_var[rows][:, vis]
        R = _writable(np.broadcast_to(relnav.measurement_noise(fs, setup, nvis, av, fv), (b, m)))
    alpha = _writable(step.alpha if every else step.alpha[rows]) if setup.pseudo else zeros3
    keep = None if step.feature_mask is None else step.feature_mask[rows]
    offered = None if step.offered is None else step.offered[rows]
    if offered is not None and keep is None:
        keep = offered
    model = step_model(setup, vis, nd, ndd)
    if fs.gate_probability is not None and nvis:
        from . import gating

        d2 = gate_distances(x, P, y, R, alpha, model, cols, chart, nvis, C, offered)
        keep, rejected, lam = gating.robust_gate(d2, fs.gate_probability, C, keep, fs.gate_inflate)
        P = gating.inflated(P, lam)
    if keep is not None:
        used = keep.sum(axis=-1)
    mask = ones if keep is None else _row_mask(keep, b, m, C)
    args = (x, P, y, R, mask, model, alpha, cols, chart)
    if x_true is None:
        xt = _no_truth(x.shape[1])
    else:
        xt = x_true if x_true.ndim == 1 or every else x_true[rows]
        xt = _writable(np.broadcast_to(xt, x.shape))
    judge = (xt, chart == CHART_ATTITUDE)  # the NEES's attitude error state (mc.trial.nees_and_pd): the attitude chart's P
    if iterated is None:
        xo, Po, nu, nis, ok, Lo, ev = ku.ekf_update_batch(*args, *judge)
        its, conv = one_iteration, converged
    else:
        xo, Po, nu, nis, its, conv, ok, Lo, ev = ku.iekf_update_batch(*args, iterated["tol"], iterated["max_iter"],
            ku.CONTROL[iterated["control"]], ku.STOPPING[iterated["stopping"]], 10, *judge)  # fmt: skip
    ev, epd, ax = (None, None, None) if x_true is None else (ev[:, :8], ev[:, 8], ev[:, 9:])  # views: patch writes
    Lo = Lo if Lo.shape[0] == b else None  # (given the truth the kernels keep P+'s square root to the NEES)
    u = relnav.GatedUpdate(xo, Po, nu, nis, its, conv, rejected, used, Lo, ev, epd, ax)
    k = b - np.count_nonzero(ok)
    if k:  # a Cholesky factorization failed: those trials take the numpy path (its solvers)
        if offered is not None:  # ... on their own features only (numpy's algebra is not blind to masked rows)
            raise NotMaskable("a factorization of the update kernels failed")
        bad = ~ok
        if 1 < k <= ONE_BY_ONE:  # the caller updates them one by one: no batch attempt first
            raise PartialUpdateError(u, bad, "left to numpy's update", tried=False)
        try:
            u = patch(u, bad, numpy_update(x[bad], P[bad], step, rows[bad], fs, setup))
        except np.linalg.LinAlgError as exc:
            raise PartialUpdateError(u, bad, str(exc)) from exc
    return u


class NotMaskable(Exception):
    """A batch updated as one with its trials' own views as row masks (``relnav.StepMeasurement.offered``) has a trial
    that numpy's algebra would update (a failed factorization) or gate: numpy's would see the masked rows of the
    others' features, so the caller (``mc.trial._update``) updates the step per pattern of visible features
    instead, each trial with exactly its own. Not a ``LinAlgError``: no bisection of the batch."""


def masks_visibility(fs: FilterSetup, n: int) -> bool:
    """Whether a dispersed batch (per-trial visibility) is updated as one, each trial's view a row mask of the union
    of the batch's views (``relnav.StepMeasurement.offered``), instead of once per pattern of visible features
    (``mc.trial._update``): for a filter whose every update runs on the update kernels (``kernel_update``,
    ``supported``), with more than ``whiten.LARGE_N`` (64) columns in ``P`` (``n``).

    There a masked row costs its ``h`` and ``H`` (16 values) and nothing in the ``n x n`` system
    (``whiten._whiten_information`` forms it from the information of the rows that are not zero), and it changes
    none of the trial's numbers: its ``H`` row is zero and its residual ``y - h`` exactly 0, so every sum over the
    rows adds exact zeros in the same order; the gate's blocks are per feature, and those out of view are not
    formed (``core.kernels.gate``). Below ``LARGE_N`` the rows' Gram product costs every row of the union for every
    trial, more than the calls per pattern save.
    """
    return n > LARGE_N and registry.steps(fs, "compiled").update is kernel_update and supported(fs)


class PartialUpdateError(np.linalg.LinAlgError):
    """The compiled update went through for every trial but ``bad``, which are left to numpy's update: it failed on
    them as a batch (``tried``), or (2 to ``ONE_BY_ONE`` trials) it was not tried on them as a batch.

    ``update`` holds the good trials' results (``bad``'s rows are to be replaced): the caller
    (``mc.trial._robust_update``) updates ``bad`` alone with numpy's update (one by one, or
    bisected) instead of computing the whole batch again. The same results as a bisection of the
    whole batch, since every kernel treats trials independently.
    """

    def __init__(self, update: relnav.GatedUpdate, bad: Array, message: str, tried: bool = True):
        super().__init__(message)
        self.update, self.bad, self.tried = update, bad, tried


def patch(u, bad: Array, v):
    """``u`` with the trials ``bad`` replaced by those of update ``v`` (same fields; where ``v`` has no
    ``P_factor``, ``nees``, ``nees_pd`` or ``axes``, those trials' are NaN: not given, not evaluated).

    Written into ``u``'s own arrays where they can be (the kernels' fresh outputs, which
    nothing else holds: no copy of a ``(B, n, n)`` covariance per step with a failure);
    a read-only field (a per-configuration constant that steps share, ``_constants``) is
    copied first. ``u`` is not to be used after.
    """
    import dataclasses

    out = {}
    for f in dataclasses.fields(u):
        a, b = getattr(u, f.name), getattr(v, f.name, None)
        if a is None:  # an optional field that u does not have (P_factor, nees, nees_pd, axes)
            out[f.name] = None
            continue
        if not (isinstance(a, np.ndarray) and a.flags.writeable):
            a = np.array(a, copy=True)
        a[bad] = np.nan if b is None else b  # (only the optional fields can be missing from v: NaN marks them)
        out[f.name] = a
    return type(u)(**out)


def supported(fs: FilterSetup) -> bool:
    """Filters the compiled update covers (others run ``estimators.update``): the EKF, the IEKF and the MEKF in
    any chart (full state, aligned or attitude error state), their iterated updates with any step control and
    stopping test, and the UKF's iterated first update (its other updates are ``ukf.update`` on the compiled model)."""
    if chart_code(fs) is None:
        return False
    it = fs.iteration(True)  # the knobs of its iterated updates (None: it has none)
    return it is None or (it.step_control in ku.CONTROL and it.stopping in ku.STOPPING)
