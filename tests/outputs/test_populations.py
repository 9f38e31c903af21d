"""Percentile tables say which trials they hold; parameters the data did not reveal are named (issue 10)."""

import pandas as pd

from stereopose_mc.outputs import consistency
from stereopose_mc.rundir import percentiles
from stereopose_mc.rundir.tables import ERROR_NAMES


def frame():
    return pd.DataFrame({
        "trial": [0, 1, 2, 3], "filter": ["iekf"] * 4, "lost": [False, True, False, True],
        "lost_reason": ["", "covariance not positive definite", "", "filter lost: mean NIS over 10 steps = 300"],
        "inconsistent": [False, False, True, False],
        "inconsistent_reason": ["", "", "inconsistent: k error >= 40 x its claimed sigma over 10 steps > 30", ""],
        "final_sigma_ratio_k1": [0.9, 0.1, 0.8, 0.2], "final_sigma_ratio_k2": [0.1, 0.9, 0.2, 0.9],
        "nees_gauge_mean": [26.0, 1e6, 52.0, 1e6], "nis_ratio_mean": [1.0, 50.0, 1.02, 50.0], "nis_dof_mean": [43.0] * 4,
    })  # fmt: skip


def test_population_note_lists_the_lost_and_the_inconsistent_trials_by_kind():
    note = percentiles.population_note(frame(), "iekf")
    lost, incons = note.split("Inconsistent trials")
    assert "- filter lost: mean NIS (1): 3" in lost and "- covariance not positive definite (1): 1" in lost
    assert "errors of those not lost count" in incons and "- inconsistent: k error (1): 2" in incons
    assert "left out of `converged` too" in percentiles.population_note(frame(), "iekf", exclude_inconsistent=True)
    assert percentiles.population_note(frame().assign(lost=False, inconsistent=False), "iekf").startswith("No trial was lost")


def test_percentiles_count_inconsistent_trials_unless_excluded():
    f = frame().assign(**{n: [1.0, 2.0, 3.0, 4.0] for n in ERROR_NAMES})
    pt = percentiles.percentile_table(f, [100])
    conv = pt[pt["population"] == "converged"].iloc[0]
    assert conv["trials"] == 2 and conv["e_rho"] == 3.0  # trials 0 and 2 (inconsistent, counted)
    assert (conv["lost"], conv["inconsistent"], conv["diverged"]) == (2, 1, 2)
    ex = percentiles.percentile_table(f, [100], exclude_inconsistent=True)
    conv = ex[ex["population"] == "converged"].iloc[0]
    assert conv["trials"] == 1 and conv["e_rho"] == 1.0
    assert ex[ex["population"] == "all"].iloc[0]["e_rho"] == float("inf")


def test_wilson_interval_is_scipys():
    from scipy.stats import binomtest

    ci = binomtest(72, 100).proportion_ci(method="wilson")
    assert percentiles.wilson_interval(72, 100) == (ci.low, ci.high)
    assert abs(ci.low - 0.62512) < 1e-5 and abs(ci.high - 0.79860) < 1e-5  # by hand: centre 0.7119, half-width 0.0868
    assert percentiles.rate_text(72, 100) == "72 of 100 (72 %, 95 % CI 63-80 %)"


def test_not_observable_uses_the_converged_trials_final_sigma():
    # converged trials 0 and 2: k1 kept 0.9 and 0.8 of its sigma (median 0.85), k2 0.1 and 0.2
    got = percentiles.not_observable(frame(), "iekf")
    assert list(got) == ["k1"] and abs(got["k1"] - 0.85) < 1e-12


def test_consistency_summary_and_verdict_in_words():
    c = consistency.summarize(frame(), "iekf", 30, 91)
    assert c.trials == 2 and abs(c.nees["nees_gauge"] - 39.0 / 26) < 1e-12
    assert c.nis_inside and c.consistent and c.verdict().endswith(": consistent.")
    bad = consistency.summarize(frame().assign(nees_gauge_mean=[260.0, 0, 520.0, 0]), "iekf", 30, 91)
    assert not bad.consistent and "overconfident in the gauge-projected state" in bad.verdict()
