"""docs/make_validation.py: the verdict logic on tiny synthetic runs, and the committed docs/validation.md.

The statement functions are fed hand-made trials tables whose medians are known by
construction, so each verdict follows from the stated rule by hand. The committed doc
must cover the six cases and every cell of its tables must equal the row of
docs/validation/summary.csv that the script wrote with it.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from doc_scripts import load_doc_script

from stereopose_mc.data import thesis_percentiles
from stereopose_mc.rundir.tables import ERROR_NAMES

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "validation.md"
SUMMARY = ROOT / "docs" / "validation" / "summary.csv"


mv = load_doc_script("make_validation")

BASE = {"e_rho": 0.5, "e_rho_dot": 1e-3, "e_omega": 5e-4, "e_theta": 0.7, "e_k1": 0.03, "e_k2": 0.02}


def frame(label: str, n: int, errs: dict[str, float], diverged: int = 0, reason: str = "filter lost: x = 1",
          final: dict[str, float] | None = None) -> pd.DataFrame:  # fmt: skip
    """``n`` trials of one filter; every converged trial has exactly the errors ``errs`` (so they are the medians);
    the last ``diverged`` trials are diverged with ``reason``."""
    div = np.arange(n) >= n - diverged
    d = {"trial": np.arange(n), "filter": label, "diverged": div, "diverged_step": np.where(div, 19, -1),
         "diverged_reason": np.where(div, reason, ""), "nees_mean": np.where(div, np.nan, 30.0)}  # fmt: skip
    for name in ERROR_NAMES:
        d[name] = np.where(div, np.nan, errs[name])
        d[f"final_{name}"] = np.where(div, np.nan, (final or errs)[name])
    return pd.DataFrame(d)


CONFIG = {"initial_covariance": {"k": 0.5}, "filters": [{"type": "iekf"}, {"type": "ekf"}],
          "truth_initial_state": {"omega_degps": [-1.0, -1.0, 0.934]}, "time": {"duration_s": 100.0}}  # fmt: skip


def stats(case: str, iekf: dict, ekf: dict | None = None, ekf_div: int = 0, iekf_div: int = 0, ts=None,
          n: int = 20, reason: str = "filter lost: x = 1", final: dict | None = None):  # fmt: skip
    parts = [frame("iekf", n, iekf, iekf_div, reason, final)]
    if ekf is not None:
        parts.append(frame("ekf", n, ekf, ekf_div, reason))
    return mv.case_stats(case, pd.concat(parts, ignore_index=True), ts, None, CONFIG)


def scaled(f: float | dict[str, float], base=BASE) -> dict[str, float]:
    return {n: base[n] * (f[n] if isinstance(f, dict) else f) for n in ERROR_NAMES}


# ----------------------------------------------------------------------------- small pieces


def test_reason_groups_and_combine():
    assert mv.reason_group("error bound exceeded: e_k1 = 21 > 20") == "error bound"
    assert mv.reason_group("filter lost: mean NIS over 10 steps = 300 x its dimension > 100") == "lost (NIS)"
    for r in ("non-finite state or covariance", "covariance not positive definite",
              "linear algebra failure in the update: Singular matrix"):  # fmt: skip
        assert mv.reason_group(r) == "numerical"
    assert mv.reason_detail("error bound exceeded: e_k1 = 21 > 20") == "error bound exceeded: e_k1"
    assert mv.reason_detail("linear algebra failure in the update: Singular matrix") == \
        "linear algebra failure in the update"
    assert mv.combine([True, True]) == mv.AGREES
    assert mv.combine([True, False]) == mv.PARTLY
    assert mv.combine([False, False]) == mv.DISAGREES
    assert mv.combine([True, None]) == mv.UNTESTABLE


def test_consistency_verdicts():
    assert mv.nees_verdict(29.0, 29) == "consistent"
    assert mv.nees_verdict(3 * 29 + 1, 29) == "overconfident"
    assert mv.nees_verdict(29 / 3 - 0.1, 29) == "underconfident"
    assert mv.nis_verdict(1.04) == "consistent"
    assert mv.nis_verdict(1.3) == "too large"
    assert mv.nis_verdict(0.7) == "too small"


def test_block_nees_matches_hand_computation():
    rng = np.random.default_rng(1)
    B, n = 4, 7
    s = rng.uniform(0.5, 2.0, (B, n))
    P = np.zeros((B, n, n))
    P[:, np.arange(n), np.arange(n)] = s**2
    e = rng.normal(size=(B, n))
    blocks = {"a": slice(0, 3), "b": slice(3, 7)}
    got = mv.block_nees(e, P, blocks)
    np.testing.assert_allclose(got["a"], np.sum((e[:, :3] / s[:, :3]) ** 2, axis=1), rtol=1e-12)
    np.testing.assert_allclose(got["b"], np.sum((e[:, 3:] / s[:, 3:]) ** 2, axis=1), rtol=1e-12)
    # a derived quantity y = 2 x: e_y = 2 e, cov 4 P -> the same NEES
    J = np.broadcast_to(2 * np.eye(n), (B, n, n))
    np.testing.assert_allclose(mv.linear_nees(2 * e, J, P), got["a"] + got["b"], rtol=1e-10)


# ----------------------------------------------------------------------------- findings


def test_iekf_vs_ekf_slightly_better_or_more():
    assert mv.finding_iekf_vs_ekf(stats("A", BASE, scaled(1.2))).verdict == mv.AGREES
    f = mv.finding_iekf_vs_ekf(stats("A", BASE, scaled(3.0)))
    assert f.verdict == mv.PARTLY and "by more than 'slightly'" in f.evidence
    assert mv.finding_iekf_vs_ekf(stats("A", BASE, scaled(0.8))).verdict == mv.DISAGREES
    # EKF 1.2 x but diverging in 5 of 20 trials: better, not slightly
    assert mv.finding_iekf_vs_ekf(stats("A", BASE, scaled(1.2), ekf_div=5)).verdict == mv.PARTLY
    # too few paired trials: decided by divergence alone
    f = mv.finding_iekf_vs_ekf(stats("B", BASE, scaled(1.2), ekf_div=18))
    assert f.verdict == mv.PARTLY and "too few to pair" in f.evidence


def test_ekf_few_divergences_mostly_in_k():
    k_big = scaled({**{n: 1.1 for n in ERROR_NAMES}, "e_k1": 10.0, "e_k2": 8.0})
    assert mv.finding_ekf_few_k(stats("B", BASE, k_big, ekf_div=2)).verdict == mv.AGREES  # 2 of 20 = 10 %
    assert mv.finding_ekf_few_k(stats("B", BASE, k_big, ekf_div=3)).verdict == mv.PARTLY  # 15 %: not 'a few'
    omega_big = scaled({**{n: 1.1 for n in ERROR_NAMES}, "e_omega": 30.0, "e_k1": 10.0})
    assert mv.finding_ekf_few_k(stats("B", BASE, omega_big, ekf_div=1)).verdict == mv.PARTLY
    assert mv.finding_ekf_few_k(stats("B", BASE, omega_big, ekf_div=0)).verdict == mv.DISAGREES


def test_like_reference_case():
    b = stats("B", BASE)
    assert mv.finding_like_reference(stats("C", scaled(1.5)), b, "x").verdict == mv.AGREES
    assert mv.finding_like_reference(stats("C", scaled(2.5)), b, "x").verdict == mv.PARTLY
    assert mv.finding_like_reference(stats("C", scaled(2.5), iekf_div=2), b, "x").verdict == mv.DISAGREES
    assert mv.finding_like_reference(stats("C", scaled(1.0), iekf_div=1), b, "x").verdict == mv.AGREES  # 5 %
    assert mv.finding_like_reference(stats("C", scaled(1.0)), None, "x").verdict == mv.UNTESTABLE


def test_case_e_and_f_inertia_rules():
    sigma = math.sqrt(0.5)  # CONFIG's initial k variance
    thr_e, thr_f = 0.5 * sigma, 0.2 * sigma

    def k(k1, k2):
        return {**BASE, "e_k1": k1, "e_k2": k2}

    assert mv.finding_e_k_stays(stats("E", k(thr_e, thr_e + 0.1))).verdict == mv.AGREES  # '>=' holds at the bound
    assert mv.finding_e_k_stays(stats("E", k(thr_e + 0.1, thr_e - 0.01))).verdict == mv.PARTLY
    assert mv.finding_e_k_stays(stats("E", k(0.1, 0.1))).verdict == mv.DISAGREES
    assert mv.finding_f_k_converge(stats("F", k(thr_f - 0.01, 0.01))).verdict == mv.AGREES
    assert mv.finding_f_k_converge(stats("F", k(thr_f, 0.01))).verdict == mv.PARTLY  # '<' fails at the bound
    e = stats("E", BASE)
    worse = mv.finding_f_worse(stats("F", scaled({**{n: 1.0 for n in ERROR_NAMES}, "e_omega": 1.3, "e_theta": 0.9})), e)
    assert worse.verdict == mv.PARTLY
    both = mv.finding_f_worse(stats("F", scaled({**{n: 1.0 for n in ERROR_NAMES}, "e_omega": 2.0, "e_theta": 3.0})), e)
    assert both.verdict == mv.AGREES
    assert mv.finding_f_translation(stats("F", scaled(0.3)), e).verdict == mv.DISAGREES
    assert mv.finding_f_translation(stats("F", scaled(1.9)), e).verdict == mv.AGREES
    rest = {**scaled(1.5), "e_k1": 0.4, "e_k2": 0.4}
    assert mv.finding_rest_fine(stats("E", rest), stats("B", BASE)).verdict == mv.AGREES


def synthetic_ts(n: int, theta0: float, nis1: float = 43.0 * 5) -> pd.DataFrame:
    """Three steps (t = 0, 10, 20 s) of ``n`` trials of the IEKF: theta(0) = ``theta0``; NIS/dof 1 after step 1."""
    rows = []
    for i in range(n):
        for step, t in enumerate((0.0, 10.0, 20.0)):
            r = {"trial": i, "filter": "iekf", "step": step, "t": t, "nis_dof": 43.0 if step else 0.0,
                 "nis": np.nan if step == 0 else (nis1 if step == 1 else 43.0), "nees": 30.0}  # fmt: skip
            r.update({name: BASE[name] for name in ERROR_NAMES})
            r["e_theta"] = theta0 if step == 0 else 0.9 * theta0
            rows.append(r)
    return pd.DataFrame(rows)


def test_attitude_rule_uses_initial_and_final_medians():
    ts = synthetic_ts(6, theta0=1.0)
    stays = stats("A", BASE, ts=ts, n=6, final={**BASE, "e_theta": 0.8})
    assert stays.initial_median["e_theta"] == 1.0
    assert mv.finding_attitude(stays).verdict == mv.AGREES  # 0.8 > 0.5: the thesis's 'poor convergence' holds
    conv = stats("A", BASE, ts=ts, n=6, final={**BASE, "e_theta": 0.5})
    assert mv.finding_attitude(conv).verdict == mv.DISAGREES
    assert mv.finding_attitude(stats("A", BASE)).verdict == mv.UNTESTABLE  # no time series
    # NIS ratios from the same series: first update 5 x dof, then exactly 1
    i = stays.by_kind("iekf")
    assert i.nis_first == pytest.approx(5.0) and i.nis_after == pytest.approx(1.0)


def test_old_nis_window_flags_only_when_the_window_reaches_before_the_start():
    ts = synthetic_ts(3, 1.0, nis1=43.0 * 5000)
    # window of 2 steps, start 15 s: the check at t = 20 s spans steps 1..2 (t = 10, 20 s), reaching before the
    # start; its mean NIS/dof is (5000 + 1) / 2
    old = {"nis_window_steps": 2, "nis_start_s": 15.0}
    assert mv.old_nis_window_lost(ts, "iekf", {**old, "nis_ratio": 2500}) == 3
    assert mv.old_nis_window_lost(ts, "iekf", {**old, "nis_ratio": 2501}) == 0
    # start 10 s: that window lies after the start, which the fixed rule (and not the old one alone) uses
    assert mv.old_nis_window_lost(ts, "iekf", {"nis_window_steps": 2, "nis_start_s": 10.0, "nis_ratio": 100}) == 0


def test_side_by_side_table_holds_thesis_and_our_percentiles():
    cs = stats("D", BASE, scaled(2.0), ekf_div=20)  # the EKF lost every trial
    side, alltab = mv.side_by_side(cs)
    th = thesis_percentiles("D").set_index("percentile")
    rows = {(r[0], r[1]): r[2:] for r in side.rows}
    assert rows[("50", "thesis Table 6.4")] == [th.at[50.0, n] for n in ERROR_NAMES]
    assert rows[("90", "IEKF (20 conv.)")] == pytest.approx([BASE[n] for n in ERROR_NAMES])
    assert all(math.isnan(v) for v in rows[("50", "EKF (0 conv.)")])
    assert alltab is not None and all(v == math.inf for v in alltab.rows[1][2:])  # EKF, all trials, p50


def test_table_markdown_round_trip():
    t = mv.Table("t1", ["case", "x", "y"], 1)
    t.add("A", 0.000123456, "note")
    t.add("B", math.inf, None)
    parsed = parse_tables(t.markdown())["t1"]
    recs = {(r["row"], r["column"]): r for r in t.records()}
    for row in parsed["rows"]:
        for h, cell in zip(parsed["headers"][1:], row[1:]):
            assert recs[(row[0], h)]["text"] == cell
    assert parsed["rows"][0][1] == "0.000123"


# ----------------------------------------------------------------------------- the committed doc


def parse_tables(text: str) -> dict[str, dict]:
    """Every ``<!-- table:KEY keys=N -->`` table of a markdown text: headers, key count and rows of cells."""
    out = {}
    lines = text.splitlines()
    for i, line in enumerate(lines):
        m = re.match(r"<!-- table:(\S+) keys=(\d+) -->", line)
        if not m:
            continue
        headers = [c.strip() for c in lines[i + 1].strip().strip("|").split("|")]
        rows = []
        for row in lines[i + 3 :]:
            if not row.startswith("|"):
                break
            rows.append([c.strip() for c in row.strip().strip("|").split("|")])
        out[m.group(1)] = {"headers": headers, "keys": int(m.group(2)), "rows": rows}
    return out


@pytest.mark.skipif(not DOC.is_file(), reason="docs/validation.md not generated yet (make validation)")
def test_committed_doc_covers_all_cases_and_matches_summary_csv():
    text = DOC.read_text()
    for c in "ABCDEF":
        assert f"## Case {c}\n" in text
        assert f"table:case{c}-percentiles " in text
    assert "make validation" in text and "took" in text
    tabs = parse_tables(text)
    # every markdown table in the doc is a marked (checked) one
    assert text.count("\n|---") == len(tabs) > 0
    summ = pd.read_csv(SUMMARY, keep_default_na=False)
    index = {(r.table, r.row, r.column): r for r in summ.itertuples()}
    assert set(summ["table"]) == set(tabs)
    n_cells = 0
    for key, t in tabs.items():
        k = t["keys"]
        for row in t["rows"]:
            label = " / ".join(row[:k])
            for h, cell in zip(t["headers"][k:], row[k:]):
                rec = index[(key, label, h)]
                assert rec.text == cell, (key, label, h)
                if re.fullmatch(r"-?\d[\d.e+-]*", cell):
                    assert float(rec.value) == pytest.approx(float(cell), rel=5e-3), (key, label, h)
                n_cells += 1
    assert n_cells == len(summ)
    # the thesis columns of the doc are the bundled thesis tables
    th = thesis_percentiles("B").set_index("percentile")
    row = next(r for r in tabs["caseB-percentiles"]["rows"] if r[:2] == ["50", "thesis Table 6.2"])
    assert [float(x) for x in row[2:]] == pytest.approx([th.at[50.0, n] for n in ERROR_NAMES])


@pytest.mark.skipif(not DOC.is_file(), reason="docs/validation.md not generated yet (make validation)")
def test_committed_figures_exist_and_are_small():
    text = DOC.read_text()
    figs = re.findall(r"\]\(validation/([^)]+\.png)\)", text)
    assert len(figs) >= 6 * 3
    for f in figs:
        assert (ROOT / "docs" / "validation" / f).is_file(), f
    total = sum(p.stat().st_size for p in (ROOT / "docs" / "validation").glob("*.png"))
    assert total < 10e6
