"""The report's per-filter summary and consistency verdict in words (issue 13, item 6)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from stereopose_mc.outputs import summary as sm


def trials_frame(lost, incons, lost_reasons, incons_reasons, label="iekf") -> pd.DataFrame:
    n = len(lost)
    return pd.DataFrame({"trial": np.arange(n), "filter": label, "lost": lost, "lost_reason": lost_reasons,
                         "lost_step": np.where(lost, 3, -1), "inconsistent": incons,
                         "inconsistent_reason": incons_reasons})  # fmt: skip


def test_band_covers_95_percent_of_means_of_chi_square_draws():
    """Independent check of the band: means of simulated chi-square(d) NEES values fall inside ~95 % of the time."""
    rng = np.random.default_rng(1)
    N, d, reps = 40, 29, 4000
    means = (rng.standard_normal((reps, N, d)) ** 2).sum(axis=2).mean(axis=1)
    lo, hi = sm.band(N, d)
    inside = np.mean((means >= lo) & (means <= hi))
    assert abs(inside - 0.95) < 0.015
    assert lo < d < hi


def test_counts_rates_kinds_and_remedies():
    n = 20
    lost = np.arange(n) < 12
    incons = (np.arange(n) >= 10) & (np.arange(n) < 15)
    lr = ["filter lost: mean NIS over 10 steps = 300 x its dimension > 100"] * 11 + ["covariance not positive definite"] \
        + [""] * 8
    ir = [""] * 10 + ["inconsistent: gauge-projected NEES >= 1e+06 over 10 steps > 10 x ..."] * 5 + [""] * 5
    t = trials_frame(lost, incons, lr, ir)
    s = sm.summarize(t, ["iekf"], {"iekf": "ekf"})[0]
    assert (s.trials, s.lost, s.inconsistent, s.kept) == (20, 12, 5, 8)
    assert s.lost_kinds == [("filter lost: mean NIS", 11), ("covariance not positive definite", 1)]
    assert s.inconsistent_kinds == [("inconsistent: gauge-projected NEES", 5)]
    assert s.rate(12) == "12 of 20 (60 %, 95 % CI 39-78 %)"
    assert sm.summarize(t, ["iekf"], {}, exclude_inconsistent=True)[0].kept == 5  # 3 not lost but inconsistent
    r = sm.remedies(s, {"type": "ekf"})
    assert len(r) == 1 and "`first_update: iterated`" in r[0] and "`initial_estimate: measurements`" in r[0]
    assert "median lost step 3" in r[0]
    assert sm.remedies(s, {"type": "ekf", "first_update": "iterated"})[0].count("first_update") == 0
    assert "`first_update: iterated`" in sm.remedies(s, {"type": "mekf"})[0]  # the MEKF has the option too
    assert sm.remedies(s, {"type": "mekf", "iterated": True})[0].count("first_update") == 0  # already iterated
    blind = sm.summarize(trials_frame(lost, incons, ["filter lost: no feature measured at any of 10 steps"] * n, ir),
                         ["iekf"], {})[0]  # fmt: skip
    assert "measured no feature" in sm.remedies(blind, {"type": "ekf"})[0]
    few = sm.summarize(trials_frame(lost & (np.arange(n) < 3), incons, lr, ir), ["iekf"], {})[0]
    assert sm.remedies(few, {"type": "ekf"}) == []  # a minority lost: nothing to advise


def test_report_leads_with_results_and_folds_the_scenario(run_dir):
    text = (run_dir / "report.html").read_text(encoding="utf-8")
    heads = [h.split("</h2>")[0] for h in text.split("<h2>")[1:]]
    assert heads[0] == "Results" and heads[-1] == "Scenario and run"
    results = text.split("<h2>Results</h2>")[1].split("<h2>")[0]
    for label in ("iekf", "ekf"):
        assert f"<b>{label}</b>:" in results
    assert "consistent" in results and "NEES/dof" in results and "95 % Wilson interval" in results
    tail = text.split("<h2>Scenario and run</h2>")[1]
    assert tail.count("<details>") == 2 and "feature_points_m" in tail


def test_histogram_axes_are_clipped_with_a_note():
    """One wild trial does not stretch the axis: it is left out and counted on the panel."""
    from matplotlib.figure import Figure

    from stereopose_mc.outputs import figures as figs

    v = np.concatenate([np.linspace(1.0, 2.0, 99), [1e4]])
    lo, hi = figs.robust_range(v)
    assert lo == 1.0 and 4.0 < hi < 4.5  # q75 + 5 IQR, quartiles about 1.25 and 1.76
    ax = Figure().subplots()
    out = figs.clipped_hist(ax, v, "k")
    assert out.tolist() == [1e4]
    assert ax.get_xlim()[1] < 10.0
    assert any("1 above (max 1e+04) not shown" in t.get_text() for t in ax.texts)
