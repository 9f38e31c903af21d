"""Whole trials through ``--kernels numpy`` and ``--kernels compiled`` agree (issue 14).

The compiled step computes the same equations in another order, so the two paths differ
by round-off. Required, in the full state and in the aligned and the attitude error states
(there the states are compared in the error state, ``aligned.local`` or
``errorstate.local``), at every step of whole case-B
trials (both filters as configured, the gated filters of case B with tracker dropouts and
outliers, the aligned MEKF and the EKF's iterated first update), from the same posterior,
for the trials
still well inside the divergence bounds: the next posterior states within 1e-8 of the
posterior standard deviation and covariances within 1e-8 relative (``P_ij`` against
``sqrt(P_ii P_jj)``). The one exception is the first update or two of a trial (filter R
~1e-10 against a prior P ~1, S conditioned ~1e8), where the numpy path itself moves by
2e-8 (IEKF) to 8e-8 (EKF) of the posterior sigma when its prior state is changed by one
ulp: there the compiled step must stay within 5x that round-off floor. (Ungated filters
fed 5 % outliers are not compared step by step: numpy's own 1-ulp floor reaches 6e-5
sigma there, and any reordering of the arithmetic moves them by a similar amount.)

Free-running trials cannot meet 1e-8 at the end: the first updates (filter R ~1e-10
against a prior P ~1) amplify round-off by ~1e8, so the numpy path *itself* moves by
~1e-4 sigma over 40 steps when its initial state is changed in the 16th digit. Whole
free-running trials are therefore required to take the same divergence decisions and
iteration counts, and to differ by no more than that numpy-vs-numpy round-off spread.
"""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest
import yaml

from stereopose_mc.config import load_scenario_text
from stereopose_mc.config.resolve import filter_setup_of, setup_of
from stereopose_mc.core import aligned, errorstate
from stereopose_mc.mc.trial import Bounds, run_chunk
from stereopose_mc.sim import measurements as meas
from stereopose_mc.sim.truth import simulate_truth

from scenarios import ROOT, scenario_dict

if str(ROOT) not in sys.path:  # the benchmark's scaling scenarios' points (as tests/test_benchmarks_smoke.py)
    sys.path.insert(0, str(ROOT))
from benchmarks.common import sphere_points  # noqa: E402


def _prepared(case="caseB", error_state="full", **overrides):
    scn = load_scenario_text(yaml.safe_dump(scenario_dict(case, **overrides)))
    setup = setup_of(scn)
    truth = simulate_truth(setup)
    # the full-state step or the aligned error state (the default): both have compiled kernels (None: as configured)
    fss = [filter_setup_of(f, setup) for f in scn.filters]
    if error_state is not None:
        fss = [dataclasses.replace(f, error_state=error_state) for f in fss]
    return scn, setup, truth, meas.noise_free(setup, truth), fss


class _Both:
    """A step whose ``predict``/``update`` run both paths, record their difference, return numpy's."""

    @staticmethod
    def sane(x, P):
        """Trials still far inside the divergence bounds (a filter blowing up is compared no further)."""
        d = np.diagonal(P, axis1=-2, axis2=-1)
        return np.isfinite(x).all(-1) & np.isfinite(P).all((-1, -2)) & (np.abs(x).max(-1) < 1e4) & (d > 0).all(-1) \
            & (d.max(-1) < 1e4)  # fmt: skip

    def __init__(self, error_state="aligned"):
        from stereopose_mc.filters import compiled, estimators

        self.np, self.nb, self.error_state = estimators, compiled, error_state
        self.dx, self.dP, self.floor, self.floorP, self.kind = [], [], [], [], []

    @staticmethod
    def deviation(xa, xb, ne, error_state="aligned"):
        """``xb - xa`` in the filter's coordinates (``ne``): the full state, or the error state at ``xa``."""
        if xa.shape[-1] == ne:
            return xb - xa
        return (aligned if error_state == "aligned" else errorstate).local(xa, xb)

    def _record(self, xa, Pa, xb, Pb):
        ok = self.sane(xa, Pa)
        xa, Pa, xb, Pb = xa[ok], Pa[ok], xb[ok], Pb[ok]
        s = np.sqrt(np.diagonal(Pa, axis1=-2, axis2=-1))
        scale = np.abs(xa)
        if xa.shape[-1] != Pa.shape[-1]:  # aligned: e_c, e_cdot, e_omega ~ rho, rho_dot, omega; delta ~ |q| = 1
            scale = np.concatenate([scale[:, :9], np.ones((len(xa), 3)), scale[:, 13:]], axis=-1)
        s = np.maximum(s, 1e6 * np.finfo(float).eps * scale)  # a sigma below the state's own round-off: that
        self.dx.append(np.max(np.abs(self.deviation(xa, xb, Pa.shape[-1], self.error_state)) / s, initial=0.0))
        self.dP.append(np.max(np.abs(Pa - Pb) / (s[..., :, None] * s[..., None, :]), initial=0.0))

    def predict(self, x, P, t, fs, setup):
        a, b = self.np.predict(x, P, t, fs, setup), self.nb.predict(x, P, t, fs, setup)
        self._record(*a, *b)
        self.kind.append("predict")
        return a

    def _second_order(self, name, x, P, *args):
        """The second-order R term ``name`` of both paths (the same to round-off on sane trials); numpy's."""
        a, b = getattr(self.np, name)(x, P, *args), getattr(self.nb, name)(x, P, *args)
        ok = self.sane(x, P)
        np.testing.assert_allclose(b[ok], a[ok], rtol=1e-10, atol=0.0)
        return a

    def flow_linearization_variance(self, x, P, setup):
        return self._second_order("flow_linearization_variance", x, P, setup)

    def pseudo_linearization_variance(self, x, P, setup, t):
        return self._second_order("pseudo_linearization_variance", x, P, setup, t)

    def update(self, x, P, step, rows, fs, setup):
        a = self.np.update(x, P, step, rows, fs, setup)  # raises first when the batch fails (then bisected)
        b = self.nb.update(x, P, step, rows, fs, setup)
        ulp = self.np.update(np.nextafter(x, np.inf), P, step, rows, fs, setup)  # numpy's own round-off floor
        self._record(a.x, a.P, b.x, b.P)
        self.kind.append("update")
        ok = self.sane(a.x, a.P)
        s = np.sqrt(np.diagonal(a.P[ok], axis1=-2, axis2=-1))
        self.floor.append(np.max(np.abs(self.deviation(a.x[ok], ulp.x[ok], s.shape[-1], self.error_state)) / s,
                                 initial=0.0))  # fmt: skip
        self.floorP.append(np.max(np.abs(a.P[ok] - ulp.P[ok]) / (s[..., :, None] * s[..., None, :]), initial=0.0))
        np.testing.assert_array_equal(a.iterations, b.iterations)
        return a


SHORT = {"time": {"dt_s": 1.0, "duration_s": 40.0, "error_window_start_s": 5.0}}
# free-running comparison: filters that converge in case B (the plain EKF is lost in nearly every trial)
FREE = {**SHORT, "filters": [{"type": "iekf"}, {"type": "ekf", "first_update": "iterated"}]}


@pytest.mark.parametrize("error_state", ["full", "aligned", "attitude"])
@pytest.mark.parametrize("case", ["caseB", "caseB-outliers"])  # the latter: tracker dropouts, outliers, gating
def test_every_step_of_whole_trials_agrees(monkeypatch, case, error_state):
    from stereopose_mc.mc import trial

    both = _Both(error_state)
    monkeypatch.setattr(trial, "step_functions", lambda kernels: both)
    scn, setup, truth, exact, filters = _prepared(case=case, error_state=error_state, **SHORT)
    if case == "caseB-outliers":  # the gated filters (the ungated ones are hit by 5 % outliers: see the docstring)
        filters = [f for f in filters if f.gate_probability is not None]
    run_chunk(scn.seed, np.arange(6), setup, truth, exact, filters, Bounds(), kernels="both")
    _steps_agree(both, filters)


@pytest.mark.parametrize("error_state", ["aligned"])
def test_every_step_of_whole_trials_with_20_points_agrees(monkeypatch, error_state):
    """Whole trials with 20 feature points (``n`` = 74: the kernels' large-``n`` path, ``_whiten_information``, the
    centered coordinates of the aligned chart and ``_posterior_covariance_rev``), with the filters that converge in
    case B (the IEKF, the EKF with an iterated first update: the plain EKF is lost, and past 20 steps its numpy
    path moves by 1e-8 sigma for one ulp): every step agrees as in case B. (The other charts: one update each,
    ``test_update_kernels_past_64_columns_equal_numpy``.)"""
    from stereopose_mc.core.kernels import whiten as kw
    from stereopose_mc.mc import trial

    both = _Both(error_state)
    monkeypatch.setattr(trial, "step_functions", lambda kernels: both)
    points = sphere_points(20, 1.5).tolist()
    scn, setup, truth, exact, filters = _prepared(error_state=error_state, target={"feature_points_m": points}, **FREE)
    assert setup.x0.size - (error_state != "full") > kw.LARGE_N
    run_chunk(scn.seed, np.arange(3), setup, truth, exact, filters, Bounds(), kernels="both")
    _steps_agree(both, filters)


@pytest.mark.parametrize("error_state", ["full", "aligned", "attitude"])
def test_every_step_of_the_mekf_and_iterated_first_update_agrees(monkeypatch, error_state):
    """The MEKF (iterated), the EKF's iterated first update and the IEKF with Levenberg-Marquardt steps run the
    compiled kernels too, in every chart (the MEKF always has an error state: ``full`` gives it the attitude
    chart, as ``mekf.chart_of``)."""
    from stereopose_mc.mc import trial

    both = _Both(error_state)
    monkeypatch.setattr(trial, "step_functions", lambda kernels: both)
    over = {**SHORT, "filters": [{"type": "mekf", "iterated": True}, {"type": "ekf", "first_update": "iterated"},
                                 {"type": "iekf", "step_control": "levenberg_marquardt", "name": "iekf_lm"}]}
    scn, setup, truth, exact, filters = _prepared(error_state=error_state, **over)
    run_chunk(scn.seed, np.arange(6), setup, truth, exact, filters, Bounds(), kernels="both")
    _steps_agree(both, filters)


def _steps_agree(both, filters):
    assert len(both.dx) > 100  # predict and update calls of both filters over the steps
    kind = np.array(both.kind)
    dx, dP = np.array(both.dx), np.array(both.dP)
    dx_update, dP_update = dx[kind == "update"], dP[kind == "update"]
    floor, floorP = np.array(both.floor), np.array(both.floorP)
    assert max(dx[kind == "predict"]) < 1e-10 and max(dP[kind == "predict"]) < 1e-8
    # beyond 1e-8 sigma and numpy's own one-ulp floor: a few early updates (a wide prior against a small R: an
    # ill-conditioned S, more so with the pseudo rows' second-order R in the first steps)
    above = ~((dx_update < 1e-8) | (dx_update < 5 * floor)) | ~((dP_update < 1e-8) | (dP_update < 5 * floorP))
    n_filters = len({f.label for f in filters})
    assert np.sum(above) <= 2 * n_filters, (dx_update, floor, dP_update, floorP)
    # where numpy's own round-off floor is small (the trial is not in a sensitive phase, e.g. just after the
    # gate inflated its prior), only the first updates differ by 1e-8 sigma
    calm = (floor < 1e-9) & (floorP < 1e-9)
    assert np.sum(((dx_update >= 1e-8) | (dP_update >= 1e-8)) & calm) <= 3 * n_filters


def _spread(case_overrides, trials):
    """Max over filters of the final-state difference (in posterior sigma) numpy vs numpy with x0 moved by 1 ulp."""
    from stereopose_mc.mc import trial
    from stereopose_mc.sim import measurements

    scn, setup, truth, exact, filters = _prepared(**case_overrides)
    a = run_chunk(scn.seed, trials, setup, truth, exact, filters, Bounds())
    real = measurements.initial_estimates
    nudged = lambda s, d: np.nextafter(real(s, d), np.inf)  # noqa: E731
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(trial.meas, "initial_estimates", nudged)
        b = run_chunk(scn.seed, trials, setup, truth, exact, filters, Bounds())
    out = 0.0
    for ra, rb in zip(a.runs, b.runs):
        ok = (ra.diverged_step < 0) & (rb.diverged_step < 0)
        sig = np.sqrt(np.diagonal(ra.P_final[ok], axis1=-2, axis2=-1))
        dev = _Both.deviation(ra.x_final[ok], rb.x_final[ok], sig.shape[-1], case_overrides.get("error_state"))
        out = max(out, float(np.max(np.abs(dev) / sig, initial=0.0)))
    return out


@pytest.mark.parametrize("error_state", ["full", "aligned", "attitude"])
def test_free_running_trials_agree_within_the_round_off_spread(error_state):
    trials = np.arange(6)
    spread = _spread({**FREE, "error_state": error_state}, trials)
    assert 1e-10 < spread < 1e-2  # round-off alone moves the numpy path this much
    _agree({**FREE, "error_state": error_state}, trials, tol=10 * spread)


def _agree(case_overrides, trials, tol):
    scn, setup, truth, exact, filters = _prepared(**case_overrides)
    a = run_chunk(scn.seed, trials, setup, truth, exact, filters, Bounds(), kernels="numpy")
    b = run_chunk(scn.seed, trials, setup, truth, exact, filters, Bounds(), kernels="compiled")
    for ra, rb in zip(a.runs, b.runs):
        np.testing.assert_array_equal(ra.diverged_step, rb.diverged_step)
        ok = ra.diverged_step < 0
        assert ok.any()
        sig = np.sqrt(np.diagonal(ra.P_final[ok], axis1=-2, axis2=-1))
        dev = _Both.deviation(ra.x_final[ok], rb.x_final[ok], sig.shape[-1], case_overrides.get("error_state"))
        assert np.max(np.abs(dev) / sig) < tol, ra.label
        Pa, Pb = ra.P_final[ok], rb.P_final[ok]
        scale = np.sqrt(np.diagonal(Pa, axis1=-2, axis2=-1))
        rel = np.abs(Pa - Pb) / (scale[..., :, None] * scale[..., None, :])
        assert np.max(rel) < tol, ra.label
        np.testing.assert_array_equal(ra.iterations[ok], rb.iterations[ok])


def test_every_step_of_the_ukf_agrees(monkeypatch):
    """The UKF under ``--kernels compiled``: its sigma points through the compiled RK4 and ``h``
    (``model.propagate_batch``, ``model.measure_h_batch``), the unscented algebra and the iterated first update
    numpy's; every step equal to the numpy UKF's to round-off, in the aligned and the attitude chart."""
    from stereopose_mc.mc import trial

    both = _Both()
    monkeypatch.setattr(trial, "step_functions", lambda kernels: both)
    over = {**SHORT, "filters": [{"type": "ukf", "first_update": "iterated"},
                                 {"type": "ukf", "error_state": "attitude", "name": "ukf_att"}]}  # fmt: skip
    scn, setup, truth, exact, filters = _prepared(error_state=None, **over)
    assert {f.kind for f in filters} == {"ukf"} and {f.error_state for f in filters} == {"aligned", "attitude"}
    run_chunk(scn.seed, np.arange(6), setup, truth, exact, filters, Bounds(), kernels="both")
    _steps_agree(both, filters)


@pytest.mark.parametrize("kernels", ["numpy", "compiled"])
def test_ukf_takes_the_features_the_tracker_dropped_out_of_its_update(kernels):
    """A feature masked out by the tracker (``step.feature_mask``) leaves the UKF's update as if it were not in view:
    the same ``x+``, ``P+`` and NIS as the update without that feature (an independent construction of the step),
    and ``features_used`` counts it out."""
    from stereopose_mc.filters import relnav
    from stereopose_mc.mc.trial import step_functions

    scn, setup, truth, exact, fss = _prepared(error_state=None, **{**SHORT, "filters": [{"type": "ukf"}]})
    fs, sf = fss[0], step_functions(kernels)
    rng = np.random.default_rng(8)
    k, B = 6, 4
    ne = setup.x0.size - 1
    A = 0.01 * rng.normal(size=(B, ne, ne))
    P = A @ np.swapaxes(A, -1, -2) + 1e-4 * np.eye(ne)
    x = aligned.chart(np.broadcast_to(truth.x[k], (B, ne + 1)), 0.01 * rng.normal(size=(B, ne)))
    vis = exact.visible[k].copy()
    y = exact.y[k] + 1e-4 * rng.normal(size=(B,) + exact.y[k].shape)
    alpha = np.broadcast_to(truth.alpha[k], (B, 3)).copy()
    drop = np.flatnonzero(vis)[2]  # the third visible feature, dropped in trials 1 and 3
    keep = np.ones((B, vis.sum()), bool)
    keep[[1, 3], 2] = False
    rows = np.arange(B)
    masked = sf.update(x, P, relnav.StepMeasurement(relnav.stack_measurement(y, vis, setup.pseudo), alpha, vis,
                                                    truth.t[k], feature_mask=keep), rows, fs, setup)  # fmt: skip
    vis_less = vis.copy()
    vis_less[drop] = False
    without = sf.update(x, P, relnav.StepMeasurement(relnav.stack_measurement(y, vis_less, setup.pseudo), alpha,
                                                     vis_less, truth.t[k]), rows, fs, setup)  # fmt: skip
    full = sf.update(x, P, relnav.StepMeasurement(relnav.stack_measurement(y, vis, setup.pseudo), alpha, vis,
                                                  truth.t[k]), rows, fs, setup)  # fmt: skip
    s = np.sqrt(np.diagonal(P, axis1=-2, axis2=-1))
    for b in (1, 3):
        dev = aligned.local(without.x[b : b + 1], masked.x[b : b + 1])[0]
        assert np.max(np.abs(dev) / s[b]) < 1e-9
        np.testing.assert_allclose(masked.P[b], without.P[b], rtol=0, atol=1e-9 * np.abs(P[b]).max())
        assert masked.nis[b] == pytest.approx(without.nis[b], rel=1e-8)
    for b in (0, 2):  # untouched trials: the update with every feature
        np.testing.assert_array_equal(masked.x[b], full.x[b])
    np.testing.assert_array_equal(masked.features_used, [vis.sum(), vis.sum() - 1, vis.sum(), vis.sum() - 1])
    assert not np.allclose(full.x[1], masked.x[1])  # the dropped feature did carry information


def test_measure_h_batch_equals_the_numpy_model():
    """``model.measure_h_batch`` (the UKF's sigma points) equals ``relnav.measurement_model``'s ``h`` and
    ``measure_batch``'s, with per-state pseudo rows."""
    from stereopose_mc.core.kernels import model as km
    from stereopose_mc.filters import compiled, relnav

    scn, setup, truth, exact, _ = _prepared(error_state="aligned", **SHORT)
    k = 7
    rng = np.random.default_rng(3)
    x = truth.x[k] + 1e-3 * rng.standard_normal((9, truth.x.shape[-1]))
    alpha = truth.alpha[k] + 1e-4 * rng.standard_normal((4, 3))
    step = relnav.StepMeasurement(np.zeros((4, 1)), alpha, exact.visible[k], truth.t[k])
    trials = rng.integers(0, 4, size=9)
    got = compiled._measurer(setup, step)(x, trials)
    ref = relnav.measurement_model(setup, step)(x, trials, jac=False)[0]
    np.testing.assert_allclose(got, ref, rtol=1e-13, atol=1e-13 * np.abs(ref).max())
    vis = np.flatnonzero(exact.visible[k]).astype(np.int64)
    _, nd, ndd = compiled._leader(setup.orbit, float(truth.t[k]))
    model = km.StepModel(vis, setup.baseline, setup.disparity, setup.focal, setup.pseudo, float(nd[0]), float(ndd[0]))
    hx, _ = km.measure_batch(x, model, np.ascontiguousarray(alpha[trials]), False)
    np.testing.assert_array_equal(got, hx)


def test_the_compiled_measurement_model_equals_numpys():
    """``compiled.measurement_model`` (numpy's update on the trials the kernels leave to it): the same ``measure(x,
    rows, jac)`` as ``relnav.measurement_model``, ``h`` and the dense ``H`` equal to round-off, the pseudo rows with
    each row's trial's acceleration; without ``jac``, no ``H`` and the same ``h``."""
    from stereopose_mc.filters import compiled, relnav

    scn, setup, truth, exact, _ = _prepared(error_state="aligned", **SHORT)
    assert setup.pseudo
    k = 7
    rng = np.random.default_rng(5)
    x = truth.x[k] + 1e-3 * rng.standard_normal((6, truth.x.shape[-1]))
    alpha = truth.alpha[k] + 1e-4 * rng.standard_normal((8, 3))
    step = relnav.StepMeasurement(np.zeros((8, 1)), alpha, exact.visible[k], truth.t[k])
    rows = np.array([0, 2, 3, 5, 6, 7])
    hx, H = compiled.measurement_model(setup, step)(x, rows)
    ref_h, ref_H = relnav.measurement_model(setup, step)(x, rows)
    assert H.shape == ref_H.shape == (6, hx.shape[1], x.shape[1])
    np.testing.assert_allclose(hx, ref_h, rtol=1e-13, atol=1e-13 * np.abs(ref_h).max())
    np.testing.assert_allclose(H, ref_H, rtol=1e-12, atol=1e-13 * np.abs(ref_H).max())
    assert not np.array_equal(hx[:, -3:], compiled.measurement_model(setup, step)(x, rows[::-1])[0][:, -3:])
    h_only, none = compiled.measurement_model(setup, step)(x, rows, jac=False)
    assert none is None
    np.testing.assert_array_equal(h_only, hx)


@pytest.mark.parametrize("kind", ["ekf", "iekf"])
@pytest.mark.parametrize("error_state", ["full", "aligned", "attitude"])
def test_the_update_evaluates_its_posteriors_nees_as_the_nees_kernel(kind, error_state):
    """Given the truth, the compiled update evaluates each posterior's NEES in the kernel, right after ``P+`` and its
    square root (``consistency._nees_one``): bit for bit ``nees_and_pd`` of its own posteriors. A trial left to
    numpy's update is not evaluated there (NaN); ``mc.trial._posterior_nees`` computes those: its NEES and ``pd``
    are ``nees_and_pd``'s on every trial. Without the truth nothing is evaluated (None)."""
    from stereopose_mc.core.kernels import consistency as kc
    from stereopose_mc.filters import compiled
    from stereopose_mc.mc import trial

    x, P, step, fs, setup = _aligned_step(kind, B=6, full=error_state == "full")
    fs = dataclasses.replace(fs, error_state=error_state)
    rows = np.arange(len(x))
    failing = [2] if kind == "ekf" else []  # the EKF kernel's Cholesky fails there: numpy's update (the IEKF raises)
    P[failing] = -P[failing]
    rng = np.random.default_rng(8)
    xt = x + 1e-3 * rng.standard_normal(x.shape)
    xt[:, 9:13] /= np.linalg.norm(xt[:, 9:13], axis=-1, keepdims=True)
    u = compiled.update(x, P, step, rows, fs, setup, x_true=xt)
    plain = compiled.update(x, P, step, rows, fs, setup)
    assert plain.nees is None and u.P_factor is None  # (given the truth, P+'s square root is the NEES's alone)
    np.testing.assert_array_equal(u.P, plain.P)
    ref, pd = kc.nees_and_pd(u.x, u.P, xt, error_state == "attitude", plain.P_factor)
    done = ~np.isnan(u.nees_pd)
    assert done.tolist() == [i not in failing for i in rows]
    assert np.isnan(u.nees[~done]).all()
    for j, key in enumerate(kc.KEYS):
        np.testing.assert_array_equal(u.nees[done, j], ref[key][done], key)
    np.testing.assert_array_equal(u.nees_pd[done] == 1.0, pd[done])
    assert pd[done].all() and np.isfinite(u.nees[done]).all()
    v, p = trial._posterior_nees(u, xt, error_state, "compiled")
    assert v.shape == (len(x), len(kc.KEYS))
    for j, key in enumerate(kc.KEYS):
        np.testing.assert_array_equal(v[:, j], ref[key], key)
    np.testing.assert_array_equal(p, pd)


@pytest.mark.parametrize("kind", ["ekf", "iekf"])
def test_past_64_columns_the_nees_take_the_centred_square_root(kind):
    """Past ``LARGE_N`` the aligned chart's update forms ``P+ = T^-1 M M^T T^-T`` in centred point coordinates
    (``core.kernels.centred``; ``T^-1 M`` is not triangular, so no factor is returned) and its NEES take ``M``
    itself (``consistency._one`` with ``centred``: the full and gauge NEES of ``T e``, ``P+`` not factorized
    again): those of ``nees_and_pd`` on its own posteriors (``P+`` factorized) to round-off, the block NEES (from
    ``P+``'s blocks) bit for bit, ``pd`` True."""
    from stereopose_mc.core.kernels import consistency as kc, whiten as kw
    from stereopose_mc.filters import compiled

    x, P, step, fs, setup = _aligned_step(kind, B=4, N=24)
    assert P.shape[-1] > kw.LARGE_N and fs.error_state == "aligned"
    rows = np.arange(len(x))
    rng = np.random.default_rng(8)
    xt = aligned.chart(x, np.einsum("bij,bj->bi", np.linalg.cholesky(P), rng.standard_normal(P.shape[:2])))
    u = compiled.update(x, P, step, rows, fs, setup, x_true=xt)
    np.testing.assert_array_equal(u.P, compiled.update(x, P, step, rows, fs, setup).P)
    ref, pd = kc.nees_and_pd(u.x, u.P, xt, False)
    assert pd.all() and (u.nees_pd == 1.0).all()
    for j, key in enumerate(kc.KEYS):
        if key in ("nees", "nees_gauge"):
            np.testing.assert_allclose(u.nees[:, j], ref[key], rtol=1e-9, err_msg=key)
        else:
            np.testing.assert_array_equal(u.nees[:, j], ref[key], key)
    assert (ref["nees_gauge"] < ref["nees"]).all()  # the gauge projected off: not the full NEES again


@pytest.mark.parametrize("kind", ["ekf", "iekf"])
@pytest.mark.parametrize("error_state", ["full", "aligned", "attitude"])
def test_the_update_gives_the_aligned_charts_per_axis_errors_as_the_axes_kernel(kind, error_state):
    """In the aligned chart the compiled update returns, beside each posterior's NEES, its per-axis errors and their
    variances, read off the blocks its block NEES form: bit for bit ``axes.axis_errors_batch`` of its own posteriors
    (before the units). The other charts and the trials left to numpy's update are not given (NaN); there
    ``mc.trial._posterior_axes`` computes them, so its result is ``axis_errors_of``'s on every trial."""
    from stereopose_mc.core.kernels import axes
    from stereopose_mc.filters import compiled
    from stereopose_mc.mc import trial

    x, P, step, fs, setup = _aligned_step(kind, B=6, full=error_state == "full")
    fs = dataclasses.replace(fs, error_state=error_state)
    rows = np.arange(len(x))
    failing = [2] if kind == "ekf" else []
    P[failing] = -P[failing]
    rng = np.random.default_rng(8)
    xt = x + 1e-3 * rng.standard_normal(x.shape)
    xt[:, 9:13] /= np.linalg.norm(xt[:, 9:13], axis=-1, keepdims=True)
    u = compiled.update(x, P, step, rows, fs, setup, x_true=xt)
    assert compiled.update(x, P, step, rows, fs, setup).axes is None  # without the truth: none
    n_ax = len(trial.AXES)
    assert u.axes.shape == (len(x), 2 * n_ax)
    given = ~np.isnan(u.axes[:, 0])
    assert given.tolist() == [error_state == "aligned" and i not in failing for i in rows]
    assert np.isnan(u.axes[~given]).all()
    code = axes.FULL if u.P.shape[-1] == x.shape[-1] else axes.CHARTS[error_state]
    ref_err, ref_sig = axes.axis_errors_batch(u.x, u.P, xt, code, np.ones(n_ax))  # unscaled
    np.testing.assert_array_equal(u.axes[given, :n_ax], ref_err[given])
    np.testing.assert_array_equal(np.sqrt(u.axes[given, n_ax:]), ref_sig[given])
    err, sig = trial._posterior_axes(u, xt, error_state, "compiled")
    want_err, want_sig = trial.axis_errors_of(u.x, u.P, xt, error_state, "compiled")
    np.testing.assert_array_equal(err, want_err)
    np.testing.assert_array_equal(sig, want_sig)
    if error_state == "aligned":  # the variances are those of the numpy twin (M P M^T's diagonal), to round-off
        num_err, num_sig = trial.axis_errors(u.x[given], u.P[given], xt[given], error_state)
        np.testing.assert_allclose(sig[given], num_sig, rtol=1e-10)
        np.testing.assert_allclose(err[given], num_err, rtol=1e-10, atol=1e-15)


def _check_square_root(u, given):
    """The compiled update's ``P_factor``: for the trials ``given`` a square root ``R = J U`` of ``P+`` (``U`` upper
    triangular with a positive diagonal, ``R^T R = P+`` to round-off: P's own Cholesky factor, reversed), the others
    marked not given (NaN at ``U[0, 0]``); the NEES from it equal those that factorize ``P+`` itself."""
    from stereopose_mc.core.kernels import consistency as kc

    R, P = u.P_factor, u.P
    n = P.shape[-1]
    given = np.broadcast_to(given, (len(P),))
    assert R.shape == P.shape
    for b in np.flatnonzero(given):
        U = R[b][::-1]
        assert np.all(np.tril(U, -1) == 0.0) and np.all(np.diag(U) > 0.0)
        np.testing.assert_allclose(U.T @ U, P[b], rtol=0, atol=1e-13 * np.abs(P[b]).max())
        np.testing.assert_allclose(U, np.linalg.cholesky(P[b]).T, rtol=0, atol=1e-11 * np.abs(U).max())
    assert np.all(np.isnan(R[~given, n - 1, 0]))
    assert [kc._factor_given(r) for r in R] == given.tolist()
    return R


def _aligned_step(kind, stopping="mahalanobis", masked=False, B=5, k=5, control="line_search", N=None, full=False):
    """A case-B aligned prior (random P, state drawn from it about the truth) and its step, with loose R.

    ``N``: that many feature points on a sphere instead of case B's five; ``full``: the prior in the full state
    (``x = x_true + L z``, quaternion renormalized) for the full-state filter."""
    from stereopose_mc.filters import relnav

    more = {} if N is None else {"target": {"feature_points_m": sphere_points(N, 1.5).tolist()}}
    scn, setup, truth, exact, fss = _prepared(error_state="full" if full else "aligned", **SHORT, **more)
    loose = dict(sigma_image=1e-3, sigma_flow=1e-3, sigma_alpha=1e-4)
    knobs = dict(stopping=stopping, step_control=control) if kind == "iekf" else {}  # the EKF's setup has none
    fs = dataclasses.replace(fss[0] if kind == "iekf" else fss[1], **loose, gate_probability=0.99 if masked else None,
                             **knobs)  # fmt: skip
    rng = np.random.default_rng(4)
    ne = setup.x0.size - (0 if full else 1)
    A = 0.02 * rng.normal(size=(B, ne, ne))
    P = A @ np.swapaxes(A, -1, -2) + 1e-4 * np.eye(ne)
    dx = np.einsum("bij,bj->bi", np.linalg.cholesky(P), rng.normal(size=(B, ne)))
    if full:
        x = truth.x[k] + dx
        x[:, 9:13] /= np.linalg.norm(x[:, 9:13], axis=-1, keepdims=True)
    else:
        x = aligned.chart(np.broadcast_to(truth.x[k], (B, ne + 1)), dx)
    vis = exact.visible[k]
    y = exact.y[k] + 1e-3 * rng.normal(size=(B,) + exact.y[k].shape)
    keep = rng.random((B, vis.sum())) > 0.2
    keep[0, 1] = True
    if masked:
        y[0, np.flatnonzero(vis)[1]] += 0.5  # an outlier for the gate
    alpha = np.broadcast_to(truth.alpha[k], (B, 3))
    step = relnav.StepMeasurement(relnav.stack_measurement(y, vis, setup.pseudo), alpha, vis, truth.t[k],
                                  feature_mask=keep if masked else None)  # fmt: skip
    return x, P, step, fs, setup


@pytest.mark.parametrize("kind,stopping,control", [("ekf", "mahalanobis", "line_search"),
                                                   ("iekf", "mahalanobis", "line_search"),
                                                   ("iekf", "scaled", "line_search"),
                                                   ("iekf", "mahalanobis", "levenberg_marquardt"),
                                                   ("iekf", "prior", "none")])  # fmt: skip
@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("error_state", ["aligned", "attitude"])
def test_error_state_update_kernels_equal_numpy_on_a_well_conditioned_step(kind, stopping, control, masked,
                                                                           error_state):  # fmt: skip
    """One error-state update (feature mask, gate, EKF or IEKF with each step control) with R loose enough that
    ``S`` is well conditioned: the compiled update equals ``mekf.update`` to round-off (1e-11 of sigma, 1e-11 of
    the covariance)."""
    from stereopose_mc.filters import compiled, mekf

    x, P, step, fs, setup = _aligned_step(kind, stopping, masked, control=control)
    assert compiled.supported(fs)
    if error_state == "attitude":  # the same prior in the attitude chart
        fs, P = dataclasses.replace(fs, error_state="attitude"), aligned.to_attitude_chart(x, P)
    assert compiled.chart_code(fs) == {"aligned": 1, "attitude": 2}[error_state]
    vis, B = step.visible, len(x)
    rows = np.arange(B)
    a = mekf.update(x, P, step, rows, fs, setup)
    b = compiled.update(x, P, step, rows, fs, setup)
    s = np.sqrt(np.diagonal(a.P, axis1=-2, axis2=-1))
    assert np.max(np.abs(_Both.deviation(a.x, b.x, P.shape[-1], error_state)) / s) < 1e-11
    assert np.max(np.abs(a.P - b.P) / (s[:, :, None] * s[:, None, :])) < 1e-11
    np.testing.assert_allclose(b.nis, a.nis, rtol=1e-10)
    np.testing.assert_allclose(b.nu, a.nu, rtol=0, atol=1e-14)
    for f in ("iterations", "converged", "rejected", "features_used"):
        np.testing.assert_array_equal(getattr(b, f), getattr(a, f), f)
    _check_square_root(b, True)
    if masked:
        assert a.rejected[0] >= 1 and (a.features_used < vis.sum()).any()
    if kind == "iekf":
        assert (a.iterations > 1).any()


@pytest.mark.parametrize("kind,control", [("ekf", "line_search"), ("iekf", "line_search"),
                                          ("iekf", "levenberg_marquardt")])  # fmt: skip
@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("error_state", ["full", "aligned", "attitude"])
def test_update_kernels_past_64_columns_equal_numpy(kind, control, masked, error_state):
    """With 20 and 30 feature points (``n`` = 74-75 and 104-105 > 64) the kernels take the large-``n`` path: the
    information form of ``A`` (``_whiten_information``), in the aligned chart in centered point coordinates, and ``A``
    factorized in reverse order for ``P+`` (``_posterior_covariance_rev``). One well-conditioned update in each
    chart (feature mask and gate, EKF or IEKF) equals the numpy update to round-off: 1e-10 of sigma and of the
    covariance in the error states; in the full state (whose prior includes the quaternion's norm direction)
    1e-9, or 5x numpy's own change when its prior moves by one ulp, whichever is larger (as the whole-trial
    tests' first updates)."""
    from stereopose_mc.core.kernels import whiten as kw
    from stereopose_mc.filters import compiled, estimators

    for N in (20, 30):
        x, P, step, fs, setup = _aligned_step(kind, masked=masked, control=control, B=3, N=N,
                                              full=error_state == "full")  # fmt: skip
        if error_state != "full":
            fs = dataclasses.replace(fs, error_state=error_state)
        if error_state == "attitude":
            P = aligned.to_attitude_chart(x, P)
        assert P.shape[-1] > kw.LARGE_N
        assert compiled.chart_code(fs) == {"full": 0, "aligned": 1, "attitude": 2}[error_state]
        rows = np.arange(len(x))
        a = estimators.update(x, P, step, rows, fs, setup)
        b = compiled.update(x, P, step, rows, fs, setup)
        s = np.sqrt(np.diagonal(a.P, axis1=-2, axis2=-1))
        tol_x = tol_P = 1e-10
        if error_state == "full":  # the full state's quaternion: numpy's own 1-ulp floor reaches 6e-7 sigma here
            u = estimators.update(np.nextafter(x, np.inf), P, step, rows, fs, setup)
            tol_x = max(1e-9, 5 * np.max(np.abs(u.x - a.x)[:, : s.shape[-1]] / s))
            tol_P = max(1e-9, 5 * np.max(np.abs(u.P - a.P) / (s[:, :, None] * s[:, None, :])))
        assert np.max(np.abs(_Both.deviation(a.x, b.x, P.shape[-1], error_state)) / s) < tol_x, N
        assert np.max(np.abs(a.P - b.P) / (s[:, :, None] * s[:, None, :])) < tol_P, N
        np.testing.assert_allclose(b.nis, a.nis, rtol=1e-9)
        for f in ("iterations", "converged", "rejected", "features_used"):
            np.testing.assert_array_equal(getattr(b, f), getattr(a, f), f)
        _check_square_root(b, error_state != "aligned")  # the centered coordinates' factor is not triangular
        if masked:
            assert a.rejected[0] >= 1


def test_a_trial_whose_kernel_cholesky_fails_takes_the_numpy_path():
    """A trial with an indefinite covariance: the EKF kernel's Cholesky of ``S`` fails, that trial is updated by
    ``mekf.update`` (numpy's solver, which does not factorize) on the compiled measurement model
    (``compiled.numpy_update``: the same bits), which equals numpy's own to round-off; the others by the kernel; the
    IEKF raises as numpy."""
    from stereopose_mc.filters import compiled, mekf

    x, P, step, fs, setup = _aligned_step("ekf")
    P[2] = -P[2]
    rows = np.arange(len(x))
    a = mekf.update(x, P, step, rows, fs, setup)
    b = compiled.update(x, P, step, rows, fs, setup)
    one = mekf.update(x[2:3], P[2:3], step, rows[2:3], fs, setup, compiled.measurement_model)
    np.testing.assert_array_equal(b.x[2], one.x[0])
    np.testing.assert_array_equal(b.P[2], one.P[0])
    ref = mekf.update(x[2:3], P[2:3], step, rows[2:3], fs, setup)  # numpy's model
    assert np.max(np.abs(b.x[2] - ref.x[0])) <= 1e-12 * np.max(np.abs(ref.x[0]))
    np.testing.assert_allclose(b.P[2], ref.P[0], rtol=1e-9, atol=1e-12 * np.max(np.abs(ref.P[0])))
    ok = rows != 2
    _check_square_root(b, ok)  # numpy's update gives no factor
    s = np.sqrt(np.diagonal(a.P[ok], axis1=-2, axis2=-1))
    assert np.max(np.abs(aligned.local(a.x[ok], b.x[ok])) / s) < 1e-11
    x, P, step, fs, setup = _aligned_step("iekf")
    P[2] = -P[2]
    with pytest.raises(np.linalg.LinAlgError):
        mekf.update(x, P, step, rows, fs, setup)
    with pytest.raises(np.linalg.LinAlgError):
        compiled.update(x, P, step, rows, fs, setup)


def test_a_failed_update_leaves_no_reference_cycle_holding_the_batch():
    """After a partial failure and its bisection, nothing but the caller holds the batch's arrays: with the garbage
    collector off, the prior ``P`` is freed as soon as the caller drops it (an exception kept past its ``except``
    holds its traceback's frames, and their arrays, in a cycle until the collector runs: 25 MB per 250-trial
    chunk of case B accumulated that way in a first version of the bisection)."""
    import gc
    import weakref

    from stereopose_mc.filters import compiled
    from stereopose_mc.mc.trial import _robust_update

    x, P, step, fs, setup = _aligned_step("iekf", B=6)
    P[2], P[4] = -P[2], -P[4]
    rows = np.arange(len(x))
    gc.collect()
    gc.disable()
    try:
        prior = weakref.ref(P)
        u, why = _robust_update(x, P, step, rows, fs, setup, compiled.update)
        assert why[2] and why[4] and not why[0]
        del P
        assert prior() is None
    finally:
        gc.enable()


def test_a_partial_failure_is_bisected_alone_with_the_same_results():
    """Trials on which the kernel and then numpy's solvers fail: ``compiled.update`` raises ``PartialUpdateError``
    holding the others' results, and ``mc.trial._robust_update`` bisects only those trials. The result (state,
    covariance, every field, the failure reasons) is bit for bit that of bisecting the whole batch again."""
    from stereopose_mc.filters import compiled
    from stereopose_mc.mc.trial import _robust_update

    x, P, step, fs, setup = _aligned_step("iekf", B=6)
    P[2], P[4] = -P[2], -P[4]
    rows = np.arange(len(x))
    with pytest.raises(compiled.PartialUpdateError) as info:
        compiled.update(x, P, step, rows, fs, setup)
    np.testing.assert_array_equal(info.value.bad, np.isin(rows, [2, 4]))
    good = ~info.value.bad
    alone = compiled.update(x[good], P[good], step, rows[good], fs, setup)
    np.testing.assert_array_equal(info.value.update.x[good], alone.x)

    def whole_batch_bisection(*args):  # the bisection before PartialUpdateError: the compiled kernels again on halves
        try:
            return compiled.update(*args)
        except np.linalg.LinAlgError as exc:
            raise np.linalg.LinAlgError(str(exc)) from None

    sizes = []
    numpy_update = compiled.estimators.update

    def counted(x, *args, **kw):
        sizes.append(len(x))
        return numpy_update(x, *args, **kw)

    compiled.estimators.update = counted
    try:
        u, why = _robust_update(x, P, step, rows, fs, setup, compiled.update)
    finally:
        compiled.estimators.update = numpy_update
    assert sizes == [1, 1]  # numpy's update on each of the two failed trials alone: no batch attempt, no second try
    v, why_v = _robust_update(x, P, step, rows, fs, setup, whole_batch_bisection)
    assert why == why_v and [bool(r) for r in why] == [False, False, True, False, True, False]
    assert why[2].startswith("linear algebra failure in the update")
    for f in dataclasses.fields(u):
        np.testing.assert_array_equal(getattr(u, f.name), getattr(v, f.name), f.name)
    assert np.isnan(u.x[[2, 4]]).all() and np.isfinite(u.x[good]).all()


@pytest.mark.parametrize("failing", [[3], [0, 2, 3, 5, 6], list(range(1, 9)), list(range(1, 19))])
def test_the_trials_left_to_numpy_are_updated_one_by_one_with_the_bisections_results(failing):
    """Up to ``compiled.ONE_BY_ONE`` trials left to numpy's update are updated one by one without a batch attempt
    (``k`` calls), a single one not tried twice; more are tried as a batch, then bisected. Every field and reason is
    bit for bit that of the bisection of the whole batch."""
    from stereopose_mc.filters import compiled
    from stereopose_mc.mc import trial

    x, P, step, fs, setup = _aligned_step("iekf", B=max(9, len(failing) + 2))
    P[failing] = -P[failing]
    rows = np.arange(len(x))
    sizes = []
    numpy_update = compiled.estimators.update

    def counted(x, *args, **kw):
        sizes.append(len(x))
        return numpy_update(x, *args, **kw)

    def whole_batch_bisection(*args):
        try:
            return compiled.update(*args)
        except np.linalg.LinAlgError as exc:
            raise np.linalg.LinAlgError(str(exc)) from None

    compiled.estimators.update = counted
    try:
        u, why = trial._robust_update(x, P, step, rows, fs, setup, compiled.update)
    finally:
        compiled.estimators.update = numpy_update
    k = len(failing)
    assert compiled.ONE_BY_ONE <= trial.ALONE  # (the trials handed over untried are updated one by one)
    expected = [1] * k if k <= compiled.ONE_BY_ONE else [k]
    assert sizes == expected if k <= compiled.ONE_BY_ONE else sizes[0] == k and len(sizes) > k
    v, why_v = trial._robust_update(x, P, step, rows, fs, setup, whole_batch_bisection)
    assert why == why_v and [bool(r) for r in why] == [i in failing for i in rows]
    for f in dataclasses.fields(u):
        np.testing.assert_array_equal(getattr(u, f.name), getattr(v, f.name), f.name)
    _check_square_root(u, [i not in failing for i in rows])  # the trials numpy updated: marked not given


def test_patch_writes_the_kernels_arrays_in_place_and_copies_shared_constants():
    """``compiled.patch``: the failed trials' rows from the other update; ``u``'s writable arrays (the kernels'
    outputs) are written in place, a read-only one (a constant that steps share) is copied and left as it was."""
    from stereopose_mc.filters import compiled, relnav

    rng = np.random.default_rng(2)
    B, n, m = 5, 4, 3
    const = np.zeros(B, int)
    const.flags.writeable = False
    u = relnav.GatedUpdate(rng.random((B, n)), rng.random((B, n, n)), rng.random((B, m)), rng.random(B),
                           np.ones(B, int), np.ones(B, bool), const, np.full(B, 2))  # fmt: skip
    bad = np.array([False, True, False, False, True])
    v = relnav.GatedUpdate(np.full((2, n), 7.0), np.full((2, n, n), 8.0), np.full((2, m), 9.0), np.full(2, 3.0),
                           np.full(2, 4), np.zeros(2, bool), np.full(2, 5), np.full(2, 6))  # fmt: skip
    before = {f: np.array(getattr(u, f), copy=True) for f in ("x", "P", "rejected")}
    w = compiled.patch(u, bad, v)
    assert w.x is u.x and w.P is u.P  # no copy of the covariances
    assert w.rejected is not const and (const == 0).all()
    for f in dataclasses.fields(w):
        got, want = getattr(w, f.name), getattr(v, f.name)
        if f.name in ("P_factor", "nees", "nees_pd", "axes"):  # given by neither
            assert got is None and want is None
            continue
        np.testing.assert_array_equal(got[bad], want, f.name)
    np.testing.assert_array_equal(w.x[~bad], before["x"][~bad])
    np.testing.assert_array_equal(w.P[~bad], before["P"][~bad])
    np.testing.assert_array_equal(w.rejected[~bad], 0)
    # the compiled update's square roots of P: numpy's update gives none, so the patched trials' are marked not
    # given (NaN), the others' kept in place
    R = rng.random((B, n, n))
    kept = R.copy()
    u = dataclasses.replace(u, P_factor=R)
    w = compiled.patch(u, bad, v)
    assert w.P_factor is R
    assert np.isnan(w.P_factor[bad]).all()
    np.testing.assert_array_equal(w.P_factor[~bad], kept[~bad])
    # the NEES the compiled update evaluated: the patched trials' are marked not evaluated (NaN), the others kept
    ev, epd = rng.random((B, 8)), np.ones(B)
    kept = ev.copy()
    w = compiled.patch(dataclasses.replace(u, nees=ev, nees_pd=epd), bad, v)
    assert w.nees is ev and w.nees_pd is epd
    assert np.isnan(ev[bad]).all() and np.isnan(epd[bad]).all()
    np.testing.assert_array_equal(ev[~bad], kept[~bad])
    assert (epd[~bad] == 1.0).all()
    # and so are the per-axis errors it gave
    ax = rng.random((B, 28))
    kept = ax.copy()
    w = compiled.patch(dataclasses.replace(u, axes=ax), bad, v)
    assert w.axes is ax and np.isnan(ax[bad]).all()
    np.testing.assert_array_equal(ax[~bad], kept[~bad])
