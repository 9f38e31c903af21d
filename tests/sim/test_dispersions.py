"""Dispersions: sample statistics against the declared distributions, plans, streams."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from scipy import stats
from scipy.spatial.transform import Rotation
from scenarios import scenario_dict

from stereopose_mc.config import load_scenario_text
from stereopose_mc.config.resolve import setup_of
from stereopose_mc.core import state as st
from stereopose_mc.sim import dispersions as sd
from stereopose_mc.sim import measurements as meas

DEG = np.pi / 180


def scenario(dispersions: dict, **over):
    d = scenario_dict("caseB", **over)
    d["dispersions"] = dispersions
    return load_scenario_text(yaml.safe_dump(d, sort_keys=False), "<test>")


MISSION = {
    "truth_initial_state.rho_m": {"dist": "normal", "std": [2.0, 5.0, 2.0]},
    "truth_initial_state.omega_degps": {"dist": "uniform_direction", "magnitude": {"dist": "uniform", "low": 0.5,
                                                                                     "high": 3.0}},
    "truth_initial_state.q": {"dist": "uniform_rotation"},
    "target.inertia_kgm2": {"dist": "uniform", "low": [0.8, 0.9, 1.0], "high": [1.0, 1.1, 1.3], "mode": "replace"},
    "target.feature_points_m": {"dist": "truncnormal", "std": 0.1, "low": -0.2, "high": 0.2},
    "leader.orbit.e": {"dist": "uniform", "low": 0.0, "high": 0.1, "mode": "replace"},
    "camera.baseline_m": {"dist": "lognormal", "sigma": 0.01},
}  # fmt: skip


@pytest.fixture(scope="module")
def draws500():
    scn = scenario(MISSION)
    return scn, sd.draw(scn, np.arange(500))


@pytest.mark.slow
def test_500_trials_match_the_declared_distributions(draws500):
    """Per-trial truth (x0 of each trial's resolved setup) against the declared distributions."""
    scn, d = draws500
    assert not any(d.invalid)
    x0 = np.stack([setup_of(s).x0 for s in d.truth])
    n = 500
    # normal, added to the nominal [10, 60, 10]: mean within 4 standard errors, std within 15 %
    rho = x0[:, st.RHO]
    std = np.array([2.0, 5.0, 2.0])
    assert np.all(np.abs(rho.mean(0) - [10.0, 60.0, 10.0]) < 4 * std / np.sqrt(n))
    assert np.all(np.abs(rho.std(0, ddof=1) / std - 1) < 0.15)
    assert stats.kstest((rho[:, 1] - 60.0) / 5.0, "norm").pvalue > 1e-3
    # uniform, replace: inside the bounds, KS against U(low, high)
    inertia = np.array(d.values["target.inertia_kgm2"])
    lo, hi = np.array([0.8, 0.9, 1.0]), np.array([1.0, 1.1, 1.3])
    assert np.all((inertia >= lo) & (inertia <= hi))
    for i in range(3):
        assert stats.kstest(inertia[:, i], "uniform", args=(lo[i], hi[i] - lo[i])).pvalue > 1e-3
    assert np.allclose(x0[:, st.k_slice(5)], np.stack([st.k_from_inertia(v) for v in inertia]))
    # truncated normal offsets of the feature points: inside +-0.2, std of N(0, 0.1) truncated at 2 sigma
    off = x0[:, st.points_slice(5)].reshape(n, 5, 3) - np.asarray(scn.target.feature_points_m)
    assert np.abs(off).max() <= 0.2 + 1e-12
    assert abs(off.std() - stats.truncnorm(-2, 2, scale=0.1).std()) < 0.004
    # uniform direction with magnitude U(0.5, 3) deg/s: magnitudes uniform, directions uniform on the sphere
    w = x0[:, st.OMEGA] / DEG
    mag = np.linalg.norm(w, axis=-1)
    assert stats.kstest(mag, "uniform", args=(0.5, 2.5)).pvalue > 1e-3
    u = w / mag[:, None]
    assert np.all(np.abs(u.mean(0)) < 4 / np.sqrt(3 * n))  # each component has variance 1/3
    assert stats.kstest(u[:, 2], "uniform", args=(-1, 2)).pvalue > 1e-3  # Archimedes: z is uniform
    # lognormal (scale): median 1 x nominal, log-std 0.01
    b = d.values["camera.baseline_m"]
    assert abs(np.log(b).mean()) < 4 * 0.01 / np.sqrt(n) and abs(np.log(b).std(ddof=1) / 0.01 - 1) < 0.15


@pytest.mark.slow
def test_uniform_rotations_are_uniform_on_SO3(draws500):
    """Haar measure: rotation angle density (1 - cos t) / pi, and E[R] = 0."""
    _, d = draws500
    q = d.values["truth_initial_state.q"]
    assert np.allclose(np.linalg.norm(q, axis=-1), 1.0)
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]])
    angle = R.magnitude()
    cdf = lambda t: (t - np.sin(t)) / np.pi  # noqa: E731
    assert stats.kstest(angle, cdf).pvalue > 1e-3
    assert np.abs(R.as_matrix().mean(0)).max() < 4 * np.sqrt(1 / 3) / np.sqrt(500)
    # the rotated axes are uniform directions: z component of each uniform on [-1, 1]
    assert stats.kstest(R.as_matrix()[:, 2, 0], "uniform", args=(-1, 2)).pvalue > 1e-3


def test_random_plan_is_per_trial_and_keeps_other_streams():
    scn = scenario({"truth_initial_state.rho_m": {"dist": "normal", "std": 1.0}})
    a = sd.draw(scn, [3, 4, 5]).columns["truth_initial_state.rho_m[1]"]
    b = sd.draw(scn, [5]).columns["truth_initial_state.rho_m[1]"]
    assert a[2] == b[0]
    # appending a dispersion leaves the earlier ones' draws alone
    more = scenario({"truth_initial_state.rho_m": {"dist": "normal", "std": 1.0},
                     "camera.baseline_m": {"dist": "normal", "std": 0.01}})  # fmt: skip
    assert np.array_equal(sd.draw(more, [3, 4, 5]).columns["truth_initial_state.rho_m[1]"], a)
    # the noise / initial-error stream is the one of runs without dispersions
    z = meas.draw_trials(scn.seed, [4], 30, 2, 5).z0
    assert np.array_equal(z, meas.draw_trials(scn.seed, [4], 30, 2, 5).z0)
    assert not np.array_equal(sd.dispersion_rng(scn.seed, 4).random(3), np.random.default_rng(
        np.random.SeedSequence(scn.seed, spawn_key=(4,))).random(3))  # fmt: skip


@pytest.mark.parametrize("sampling", ["sobol", "lhs"])
def test_quasi_random_plans_index_by_trial(sampling):
    disp = {"sampling": sampling, "leader.orbit.e": {"dist": "uniform", "low": 0.0, "high": 0.1, "mode": "replace"},
            "camera.baseline_m": {"dist": "uniform", "low": -0.1, "high": 0.1}}  # fmt: skip
    scn = scenario(disp, trials=64)
    whole = sd.draw(scn, np.arange(64)).columns["leader.orbit.e"]
    part = sd.draw(scn, np.arange(40, 50)).columns["leader.orbit.e"]
    assert np.array_equal(whole[40:50], part)
    if sampling == "lhs":  # one point per stratum of width 0.1 / 64
        assert np.array_equal(np.sort(np.floor(whole / 0.1 * 64)), np.arange(64))
    else:  # Saltelli design: N (D + 2) rows, N = 16
        assert sd.saltelli_blocks(64, 2) == 16
        assert abs(whole.mean() - 0.05) < 0.01


def test_invalid_draws_are_flagged_with_their_reason():
    scn = scenario({"leader.orbit.a_km": {"dist": "normal", "std": 900.0}})  # a(1-e) can drop below the ground
    d = sd.draw(scn, np.arange(60))
    bad = [r for r in d.invalid if r]
    assert bad and all("below the Earth's surface" in r for r in bad)
    a = d.columns["leader.orbit.a_km"]
    assert [bool(r) for r in d.invalid] == list(a * (1 - 0.05) < 6378.137)
