"""Tracker faults (sim/faults.py) and their path through the trial loop."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from stereopose_mc.config import load_scenario_text
from stereopose_mc.config.resolve import filter_setup_of, setup_of
from stereopose_mc.config.sensor import SensorSetup
from stereopose_mc.mc.trial import Bounds, run_chunk
from stereopose_mc.sim import faults as fl
from stereopose_mc.sim import measurements as meas
from stereopose_mc.sim.truth import simulate_truth

from scenarios import scenario_dict

SHORT = {"dt_s": 1.0, "duration_s": 12.0, "error_window_start_s": 2.0}


def prepared(measurements=None, filters=None):
    d = scenario_dict(time=SHORT)
    d["measurements"].update(measurements or {})
    if filters is not None:
        d["filters"] = filters
    scn = load_scenario_text(yaml.safe_dump(d))
    setup = setup_of(scn)
    truth = simulate_truth(setup)
    exact = meas.noise_free(setup, truth)
    return scn, setup, truth, exact, [filter_setup_of(f, setup) for f in scn.filters]


def noisy_of(scn, setup, exact, trials):
    draws = meas.draw_trials(scn.seed, trials, setup.x0.size, setup.steps, setup.n_points)
    return meas.noisy(setup, exact, draws).y


def test_rates_and_independence_from_chunking():
    scn, setup, truth, exact, _ = prepared()
    sensor = SensorSetup(dropout=0.2, outlier_probability=0.1)
    trials = np.arange(40)
    y = noisy_of(scn, setup, exact, trials)
    yf, f = fl.apply_faults(sensor, scn.seed, trials, y, exact.y, exact.visible)
    n = f.kept.size
    assert abs((~f.kept).mean() - 0.2) < 4 * np.sqrt(0.2 * 0.8 / n)
    vis_kept = f.kept & exact.visible[None]
    assert abs(f.outlier.sum() / vis_kept.sum() - 0.1) < 4 * np.sqrt(0.1 * 0.9 / vis_kept.sum())
    # a sub-chunk gets the same faults and values
    sub = trials[25:31]
    yf2, f2 = fl.apply_faults(sensor, scn.seed, sub, noisy_of(scn, setup, exact, sub), exact.y, exact.visible)
    np.testing.assert_array_equal(f2.kept, f.kept[25:31])
    np.testing.assert_array_equal(yf2, yf[25:31])
    # only outliers changed, and the noise draws are untouched by the faults
    np.testing.assert_array_equal(yf[~f.outlier], y[~f.outlier])
    assert not np.any(np.all(yf[f.outlier] == y[f.outlier], axis=-1))


def test_uniform_outliers_lie_in_the_image_and_keep_the_noise():
    scn, setup, truth, exact, _ = prepared()
    sensor = SensorSetup(outlier_probability=0.5, outlier_model="uniform_image")
    trials = np.arange(10)
    y = noisy_of(scn, setup, exact, trials)
    yf, f = fl.apply_faults(sensor, scn.seed, trials, y, exact.y, exact.visible)
    noise = (y - exact.y[None])[f.outlier]
    fake = yf[f.outlier] - noise
    assert np.all(np.abs(fake[:, :4]) <= 0.5)  # default image: |u|, |v| <= 0.5
    np.testing.assert_array_equal(fake[:, 1], fake[:, 3])  # same row in both images
    np.testing.assert_allclose(fake[:, 4:8], 0.0, atol=1e-15)  # a static point


def test_swapped_outliers_take_another_features_measurement():
    scn, setup, truth, exact, _ = prepared()
    sensor = SensorSetup(outlier_probability=0.3, outlier_model="swapped_feature")
    trials = np.arange(5)
    y = noisy_of(scn, setup, exact, trials)
    yf, f = fl.apply_faults(sensor, scn.seed, trials, y, exact.y, exact.visible)
    assert f.outlier.any()
    for b, k, i in zip(*np.nonzero(f.outlier)):
        matches = [j for j in range(y.shape[2]) if j != i and np.array_equal(yf[b, k, i], y[b, k, j])]
        assert matches, (b, k, i)


def test_faults_leave_the_noise_and_initial_errors_alone_and_gating_counts():
    gate = [{"type": "ekf", "name": "ekf_gated", "gating": {"probability": 0.999}}, {"type": "ekf"}]
    scn, setup, truth, exact, filters = prepared(filters=gate)
    scn2, setup2, truth2, exact2, filters2 = prepared(
        {"dropout_probability": 0.1, "outliers": {"probability": 0.05, "model": "uniform_image"}}, filters=gate)
    trials = np.arange(6)
    clean = run_chunk(scn.seed, trials, setup, truth, exact, filters, Bounds())
    faulty = run_chunk(scn2.seed, trials, setup2, truth2, exact2, filters2, Bounds())
    np.testing.assert_array_equal(clean.runs[0].errors[:, 0], faulty.runs[0].errors[:, 0])  # same x0_hat
    assert clean.faults is None and faulty.faults is not None
    g = faulty.runs[0]
    f = faulty.faults
    kept_vis = (f.kept & exact2.visible[None]).sum(axis=-1)  # (B, K+1)
    C = 8
    active = ~np.isnan(g.errors[:, :, 0])
    used = (g.dof[:, 1:] - 3) // C
    np.testing.assert_array_equal((used + g.gated[:, 1:])[active[:, 1:]], kept_vis[:, 1:][active[:, 1:]])
    # the ungated filter uses every kept feature
    u = faulty.runs[1]
    ok = ~np.isnan(u.errors[:, 1:, 0])
    np.testing.assert_array_equal(((u.dof[:, 1:] - 3) // C)[ok], kept_vis[:, 1:][ok])
    assert (u.gated == 0).all()
    # outliers 0.5 wide against 1e-5 noise: the gate catches each of them
    assert g.gated[:, 1:].sum() >= f.outlier[:, 1:][active[:, 1:]].sum()


def test_fault_options_validate():
    with pytest.raises(Exception, match="dropout_probability"):
        prepared({"dropout_probability": 1.5})
    with pytest.raises(Exception, match="model"):
        prepared({"outliers": {"probability": 0.1, "model": "nonsense"}})


def test_gate_lockout_rule():
    from stereopose_mc.mc.trial import _gated_out

    C = 8
    # trial 0: 5 features offered, 3 gated at every step -> locked out; trial 1: one step with 2 of 5 gated
    gated = np.array([[3, 3, 3], [3, 2, 3]])
    dof = (5 - gated) * C + 3
    np.testing.assert_array_equal(_gated_out(gated, dof, C, 0.5), [True, False])
    np.testing.assert_array_equal(_gated_out(np.zeros((1, 3), int), np.full((1, 3), 3), C, 0.5), [False])


def test_faulty_gated_trials_do_not_depend_on_chunking():
    gate = [{"type": "iekf", "gating": {"probability": 0.999}}]
    scn, setup, truth, exact, filters = prepared(
        {"dropout_probability": 0.05, "outliers": {"probability": 0.05, "model": "swapped_feature"}}, filters=gate)
    batch = run_chunk(scn.seed, np.arange(4), setup, truth, exact, filters, Bounds())
    one = run_chunk(scn.seed, np.array([2]), setup, truth, exact, filters, Bounds())
    rb, r1 = batch.runs[0], one.runs[0]
    np.testing.assert_array_equal(rb.errors[2], r1.errors[0])
    np.testing.assert_array_equal(rb.gated[2], r1.gated[0])
    np.testing.assert_array_equal(rb.dof[2], r1.dof[0])
    np.testing.assert_array_equal(batch.faults.outlier[2], one.faults.outlier[0])
