"""Percentile tables say which trials they hold; parameters the data did not reveal are named (issue 10)."""

import pandas as pd

from stereopose_mc.outputs import consistency
from stereopose_mc.rundir import percentiles


def frame():
    return pd.DataFrame({
        "trial": [0, 1, 2, 3], "filter": ["iekf"] * 4, "diverged": [False, True, False, True],
        "diverged_reason": ["", "inconsistent: k error >= 40 x its claimed sigma", "", "filter lost: mean NIS"],
        "final_sigma_ratio_k1": [0.9, 0.1, 0.8, 0.2], "final_sigma_ratio_k2": [0.1, 0.9, 0.2, 0.9],
        "nees_gauge_mean": [26.0, 1e6, 52.0, 1e6], "nis_ratio_mean": [1.0, 50.0, 1.02, 50.0], "nis_dof_mean": [43.0] * 4,
    })  # fmt: skip


def test_population_note_lists_the_left_out_trials_by_reason():
    note = percentiles.population_note(frame(), "iekf")
    assert "- filter lost (1): 3" in note and "- inconsistent (1): 1" in note
    assert percentiles.population_note(frame().assign(diverged=False), "iekf").startswith("Both populations")


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
