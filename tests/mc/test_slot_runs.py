"""Feature slots in the filter loop (mc.trial.run_filter with a filters.slots.Schedule).

- the idealized point model is the special case "every slot occupied by the same track from the start": the same
  filter, bit for bit, and the same NEES to round-off;
- slots born from the first stereo frame (case B, 30 trials): consistent at birth and after, against chi-square
  bounds of the NEES over occupied slots;
- a trial's results do not depend on the trials it runs with (births and frees in other trials);
- a point that comes back after occlusion as a new track is initialized again, and the NEES count only occupied
  slots with known truth (their degrees of freedom per step).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from stereopose_mc.config import load_scenario
from stereopose_mc.core import errorstate as es
from stereopose_mc.core import layout as lay
from stereopose_mc.filters import slots as sl
from stereopose_mc.mc import engine, trial
from stereopose_mc.sim import measurements as meas

from ..scenarios import scenario_dict


@pytest.fixture(scope="module")
def case_b():
    from stereopose_mc.config.schema import Scenario

    scn = Scenario.model_validate(scenario_dict("caseB"))
    prep = engine.prepare(scn)
    B = 30
    draws = meas.draw_trials(scn.seed, np.arange(B), prep.setup.x0.size, prep.setup.steps, prep.setup.n_points)
    noisy = meas.noisy(prep.setup, prep.exact, draws)
    return prep, noisy, meas.initial_estimates(prep.setup, draws)


def _schedule(prep, B, born0=True):
    K, N = prep.setup.steps, prep.setup.n_points
    occ = np.ones((B, K + 1, N), bool)
    born = np.zeros_like(occ)
    born[:, 0] = born0
    pts = prep.truth.x[:, lay.POINTS : lay.point(N)].reshape(K + 1, N, 3)
    return sl.Schedule(occ, born, np.broadcast_to(pts, (B, K + 1, N, 3)).copy())


def _run(prep, noisy, x0, sched=None, rows=None, visible=None):
    rows = np.arange(x0.shape[0]) if rows is None else rows
    vis = prep.exact.visible if visible is None else visible[rows]
    if sched is not None:
        sched = sl.Schedule(sched.occupied[rows], sched.born[rows], sched.truth[rows])
    return trial.run_filter(x0[rows], prep.setup, prep.truth, noisy.y[rows], noisy.alpha[rows], vis, prep.filters[0],
                            prep.bounds, slots=sched)  # fmt: skip


def test_slots_held_by_the_same_tracks_are_the_point_model(case_b):
    prep, noisy, x0 = case_b
    a = _run(prep, noisy, x0)
    b = _run(prep, noisy, x0, _schedule(prep, x0.shape[0], born0=False))
    np.testing.assert_array_equal(a.x_final, b.x_final)
    np.testing.assert_array_equal(a.errors, b.errors)
    for k in ("nees_gauge", "nees_rho", "nees_attitude", "nees_feature_points", "nees_k"):
        np.testing.assert_allclose(b.nees_parts[k], a.nees_parts[k], rtol=1e-5, err_msg=k)
    assert (b.nees_dof_steps["nees_gauge"] == prep.setup.x0.size - 4).all()


def test_slots_born_from_the_first_frame_are_consistent(case_b):
    """NEES over 30 trials against the chi-square two-sided 99 % band of their sum: at birth (step 0) and averaged over
    the window t >= 10 s (gauge-projected NEES/dof median <= 2, the science target of case B)."""
    prep, noisy, x0 = case_b
    B = x0.shape[0]
    r = _run(prep, noisy, x0, _schedule(prep, B))
    assert (r.lost_step < 0).sum() >= B - 1
    for key in ("nees_feature_points", "nees_rho", "nees_gauge"):
        d = int(r.nees_dof_steps[key][0, 0])
        s = np.nansum(r.nees_parts[key][:, 0])
        lo, hi = chi2.ppf([0.005, 0.995], B * d)
        assert lo <= s <= hi, (key, s / B / d)
    g = np.nanmean(r.nees_parts["nees_gauge"][:, 10:] / r.nees_dof_steps["nees_gauge"][:, 10:], axis=1)
    assert np.nanmedian(g) <= 2.0


def test_a_trial_with_slots_is_the_same_alone(case_b):
    prep, noisy, x0 = case_b
    B = 8
    sched = _schedule(prep, x0.shape[0])
    occ = sched.occupied.copy()
    occ[3, 40:60, 2] = False  # trial 3: slot 2's track ends at step 40, a new one is born at 60
    born = sched.born.copy()
    born[3, 60, 2] = True
    sched = sl.Schedule(occ, born, sched.truth)
    vis = np.broadcast_to(prep.exact.visible, occ.shape) & occ & ~born
    allr = _run(prep, noisy, x0, sched, np.arange(B), vis)
    for j in (0, 3):
        one = _run(prep, noisy, x0, sched, np.array([j]), vis)
        np.testing.assert_array_equal(one.x_final[0], allr.x_final[j])
        np.testing.assert_array_equal(one.errors[0], allr.errors[j], strict=False)


def test_a_point_coming_back_is_born_again_and_free_slots_leave_the_nees(case_b):
    prep, noisy, x0 = case_b
    sched = _schedule(prep, 4)
    occ = sched.occupied.copy()
    occ[1, 30:50, 4] = False
    born = sched.born.copy()
    born[1, 50, 4] = True
    truth = sched.truth.copy()
    truth[2, :, 0] = np.nan  # trial 2: slot 0's true point unknown (a track born off the body)
    sched = sl.Schedule(occ, born, truth)
    vis = np.broadcast_to(prep.exact.visible, occ.shape) & occ & ~born
    r = _run(prep, noisy, x0, sched, np.arange(4), vis)
    n = prep.setup.x0.size
    d = r.nees_dof_steps
    assert (d["nees_gauge"][1, 30:50] == n - 4 - 3).all() and d["nees_gauge"][1, 50] == n - 4
    assert (d["nees_feature_points"][2] == 3 * (prep.setup.n_points - 1)).all()
    assert (d["nees_gauge"][0] == n - 4).all()
    assert (r.lost_step < 0).all()
    assert np.isfinite(r.nees_parts["nees_feature_points"][1, 30:]).all()


def test_compiled_slots_agree_with_numpy(case_b):
    """The slot operations run in numpy between the compiled steps: the two paths agree to the kernels' round-off."""
    prep, noisy, x0 = case_b
    rows = np.arange(6)
    sched = _schedule(prep, x0.shape[0])
    a = _run(prep, noisy, x0, sched, rows)
    b = trial.run_filter(x0[rows], prep.setup, prep.truth, noisy.y[rows], noisy.alpha[rows], prep.exact.visible,
                         prep.filters[0], prep.bounds, kernels="compiled",
                         slots=sl.Schedule(sched.occupied[rows], sched.born[rows], sched.truth[rows]))  # fmt: skip
    np.testing.assert_allclose(b.errors, a.errors, rtol=1e-4, atol=1e-8)  # IEKF round-off, as test_kernels_engine
    np.testing.assert_allclose(b.nees_parts["nees_gauge"], a.nees_parts["nees_gauge"], rtol=1e-4)
