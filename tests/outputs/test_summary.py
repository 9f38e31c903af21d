"""The report's per-filter summary and consistency verdict in words (issue 13, item 6)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from stereopose_mc.outputs import summary as sm


def trials_frame(nees: np.ndarray, diverged=None, reasons=None, label="iekf") -> pd.DataFrame:
    n = len(nees)
    div = np.zeros(n, bool) if diverged is None else np.asarray(diverged)
    return pd.DataFrame({"trial": np.arange(n), "filter": label, "diverged": div, "nees_mean": nees,
                         "diverged_reason": reasons if reasons is not None else [""] * n})  # fmt: skip


def test_band_covers_95_percent_of_means_of_chi_square_draws():
    """Independent check of the band: means of simulated chi-square(d) NEES values fall inside ~95 % of the time."""
    rng = np.random.default_rng(1)
    N, d, reps = 40, 29, 4000
    means = (rng.standard_normal((reps, N, d)) ** 2).sum(axis=2).mean(axis=1)
    lo, hi = sm.band(N, d)
    inside = np.mean((means >= lo) & (means <= hi))
    assert abs(inside - 0.95) < 0.015
    assert lo < d < hi


def test_verdicts_in_words():
    rng = np.random.default_rng(2)
    good = (rng.standard_normal((50, 29)) ** 2).sum(axis=1)  # NEES of a consistent filter, n - 1 = 29 dof
    s = sm.summarize(trials_frame(good), None, ["iekf"], {"iekf": "iekf"}, 30, None, str)[0]
    assert s.consistent is True and s.verdict().startswith("consistent: average NEES")
    bad = trials_frame(good * 3.0, diverged=[True] * 5 + [False] * 45,
                       reasons=["filter lost: mean NIS = 9"] * 3 + ["covariance not positive definite"] * 2 + [""] * 45)
    s = sm.summarize(bad, None, ["iekf"], {"iekf": "iekf"}, 30, None, lambda r: r.split(" = ")[0])[0]
    assert s.consistent is False and s.converged == 45
    assert "NOT consistent" in s.verdict() and "overconfident" in s.verdict()
    assert s.divergence_words() == "5 diverged: filter lost: mean NIS (3), covariance not positive definite (2)"
    low = sm.summarize(trials_frame(good / 3.0), None, ["iekf"], {}, 30, None, str)[0]
    assert "conservative" in low.verdict()
    none = sm.summarize(trials_frame(good), None, ["iekf"], {}, None, None, str)[0]
    assert none.consistent is None and "unknown" in none.verdict()


def test_report_leads_with_results_and_folds_the_scenario(run_dir):
    text = (run_dir / "report.html").read_text(encoding="utf-8")
    heads = [h.split("</h2>")[0] for h in text.split("<h2>")[1:]]
    assert heads[0] == "Results" and heads[-1] == "Scenario and run"
    results = text.split("<h2>Results</h2>")[1].split("<h2>")[0]
    for label in ("iekf", "ekf"):
        assert f"<b>{label}</b>:" in results
    assert "consistent" in results and "average NEES" in results
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
