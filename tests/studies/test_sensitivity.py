"""Sensitivity analysis against known answers: a linear model's Sobol indices, planted drivers."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import yaml
from scenarios import scenario_dict

from stereopose_mc.config import load_scenario_text
from stereopose_mc.rundir.tables import ERROR_NAMES
from stereopose_mc.sim import dispersions as sd
from stereopose_mc.studies import sensitivity as sens


def scenario(sampling: str, trials: int):
    d = scenario_dict("caseB", trials=trials)
    d["dispersions"] = {"sampling": sampling,
                        "camera.baseline_m": {"dist": "uniform", "low": 0.5, "high": 1.5, "mode": "replace"},
                        "leader.orbit.e": {"dist": "uniform", "low": 0.0, "high": 0.1, "mode": "replace"},
                        "truth_initial_state.rho_m": {"dist": "normal", "std": 1.0}}  # fmt: skip
    return load_scenario_text(yaml.safe_dump(d, sort_keys=False), "<test>")


def fake_trials(scn, y_of) -> pd.DataFrame:
    """A trials table whose errors are a known function of the drawn values."""
    d = sd.draw(scn, np.arange(scn.trials))
    df = pd.DataFrame({"trial": np.arange(scn.trials), "filter": "iekf", "invalid": False, **d.columns})
    y = y_of(df)
    for name in ERROR_NAMES:
        df[name] = y
    df["diverged"] = df["leader.orbit.e"] > 0.09  # divergence planted on the eccentricity
    return df


def test_spearman_finds_the_planted_driver_with_an_honest_interval():
    scn = scenario("random", 200)
    rng = np.random.default_rng(1)
    df = fake_trials(scn, lambda t: np.exp(2.0 * t["camera.baseline_m"]) + 0.2 * rng.standard_normal(len(t)))
    res = sens.analyze(df, scn)
    top = sens.drivers(res.table, "iekf", top=1)
    assert (top.loc[top["metric"] == "e_rho", "parameter"] == "camera.baseline_m").all()
    r = res.table[(res.table["metric"] == "e_rho") & (res.table["parameter"] == "camera.baseline_m")].iloc[0]
    assert r["value"] > 0.9 and r["ci_low"] < r["value"] < r["ci_high"] < 1 and r["significant"]
    # unrelated scalars: intervals cover 0 for (almost) all of them
    other = res.table[(res.table["metric"] == "e_rho") & (res.table["parameter"].str.startswith("truth_"))]
    assert ((other["ci_low"] < 0) & (other["ci_high"] > 0)).sum() >= 2
    # divergence: the eccentricity, positive (larger e diverges)
    dv = sens.drivers(res.table, "iekf", top=1)
    dv = dv[dv["metric"] == "diverged"].iloc[0]
    assert dv["parameter"] == "leader.orbit.e" and dv["value"] > 0.8


@pytest.mark.slow
def test_sobol_indices_of_a_noisy_linear_model():
    """Y = 4 u_b + u_e + noise (u uniform, noise var 1/12 from each trial's noise stream, as the engine draws it):
    S1 = ST = 16/18 and 1/18, the normal offsets 0. Block-shared noise keeps the estimators unbiased."""
    D = 5
    scn = scenario("sobol", 256 * (D + 2))
    streams = sd.noise_streams(scn, np.arange(scn.trials))
    noise = np.array([np.random.default_rng(int(k)).standard_normal() for k in streams]) / np.sqrt(12)
    df = fake_trials(scn, lambda t: 4.0 * (t["camera.baseline_m"] - 0.5) + t["leader.orbit.e"] / 0.1 + noise)
    res = sens.analyze(df, scn)
    s = res.sobol[(res.sobol["metric"] == "e_rho")].set_index("factor")
    assert s.loc["camera.baseline_m", "S1"] == pytest.approx(16 / 18, abs=0.04)
    assert s.loc["camera.baseline_m", "ST"] == pytest.approx(16 / 18, abs=0.04)
    assert s.loc["leader.orbit.e", "ST"] == pytest.approx(1 / 18, abs=0.02)
    assert s.loc["truth_initial_state.rho_m[1]", "ST"] == pytest.approx(0.0, abs=0.01)


def test_sobol_blocks_share_their_noise_stream():
    D = 5
    scn = scenario("sobol", 3 * (D + 2))
    k = sd.noise_streams(scn, np.arange(scn.trials)).reshape(3, D + 2)
    assert (k[:, : D + 1] == 2 * np.arange(3)[:, None]).all() and (k[:, -1] == 2 * np.arange(3) + 1).all()
    assert np.array_equal(sd.noise_streams(scenario("random", 10), np.arange(10)), np.arange(10))
