"""Figures, report.html, index.html and broken run directories."""

from __future__ import annotations

import base64
import re
import shutil
import struct
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from outputs.output_helpers import copy_run, spmc

from stereopose_mc.data import thesis_case, thesis_percentiles
from stereopose_mc.outputs import figures as figs
from stereopose_mc.outputs import report as rep
from stereopose_mc.rundir.tables import ERROR_NAMES

FULL_STEMS = ["hist-iekf", "hist-ekf", "diff-ekf-iekf", "time-iekf", "axes-iekf", "time-ekf", "axes-ekf", "nees-iekf",
              "nees-ekf", "nis-iekf", "nis-ekf", "runtime"]  # fmt: skip
PNG_SIG = b"\x89PNG\r\n\x1a\n"


def png_chunks(data: bytes) -> dict[bytes, bytes]:
    """The PNG's chunks before the image data (IHDR, pHYs, ...)."""
    assert data[:8] == PNG_SIG
    out, i = {}, 8
    while i < len(data):
        (n,) = struct.unpack(">I", data[i : i + 4])
        kind = data[i + 4 : i + 8]
        if kind == b"IDAT":
            break
        out[kind] = data[i + 8 : i + 8 + n]
        i += 12 + n
    return out


def strip_data_uris(text: str) -> str:
    return re.sub(r"data:image/png;base64,[A-Za-z0-9+/=]+", "data:image/png;base64,", text)


# --------------------------------------------------------------------------- the report of a full run


def test_spmc_run_writes_every_figure_as_png_150dpi_and_svg(run_dir):
    fig_dir = run_dir / "figures"
    for stem in FULL_STEMS:
        png, svg = fig_dir / f"{stem}.png", fig_dir / f"{stem}.svg"
        ch = png_chunks(png.read_bytes())
        w, h = struct.unpack(">II", ch[b"IHDR"][:8])
        ppm_x, ppm_y = struct.unpack(">II", ch[b"pHYs"][:8])
        assert ppm_x == ppm_y == round(150 / 0.0254), stem  # 150 dpi in pixels per metre
        assert w > 900 and h > 500, stem
        root = ET.parse(svg).getroot()
        assert root.tag.endswith("svg"), stem
    for name in ("percentiles-iekf.csv", "percentiles-iekf.md", "percentiles-ekf.csv", "percentiles-ekf.md",
                 "compute_time.csv", "compute_time.md"):  # fmt: skip
        assert (fig_dir / name).is_file(), name


def test_figures_drawn_by_two_processes_are_the_same_files(run_dir, tmp_path):
    """``jobs = 2``: the figures drawn and saved in loky processes, byte for byte the files of one process (the
    fixture's report, ``spmc run --jobs 1``), the progress told of every figure in the planned order, the same
    report.html."""
    d = copy_run(run_dir, tmp_path / "j2")
    told: list[str] = []
    report = rep.build_run_report(d, told.append, jobs=2)
    files = {k: {p.name: p.read_bytes() for p in (r / "figures").iterdir()} for k, r in ((1, run_dir), (2, d))}
    assert set(files[1]) >= {f"{s}.{e}" for s in FULL_STEMS for e in ("png", "svg")}
    assert files[1] == files[2]
    planned = ["hist-iekf", "hist-ekf", "diff-ekf-iekf", *[f"{k}-{f}" for f in ("iekf", "ekf")
                                                          for k in ("time", "axes", "nees", "nis")], "runtime"]
    assert told == planned  # (as one process tells them: the plan's order, figures.plan_figures)
    assert (run_dir / "report.html").read_text().replace(str(run_dir), str(d)) == report.read_text()


def test_spmc_report_jobs_option(run_dir, tmp_path):
    """``spmc report DIR --jobs 2``: the report and every figure written; ``--jobs 0`` refused (exit 2)."""
    d = copy_run(run_dir, tmp_path / "run")
    r = spmc("report", d, "--jobs", 2, "--quiet")
    assert r.exit_code == 0, r.output
    assert r.output.split() == [str(d / "report.html")]
    assert all((d / "figures" / f"{stem}.svg").is_file() for stem in FULL_STEMS)
    assert spmc("report", d, "--jobs", 0).exit_code == 2


def test_report_html_is_self_contained_and_embeds_every_figure(run_dir):
    text = (run_dir / "report.html").read_text()
    bare = strip_data_uris(text)
    for bad in ('src="http', "src='http", 'href="http', "<script", "<link", "url(", "@import", "<iframe"):
        assert bad not in bare, bad
    uris = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)
    assert len(uris) == len(FULL_STEMS)
    for u in uris:
        assert base64.b64decode(u)[:8] == PNG_SIG
    # the embedded image is the saved file
    assert base64.b64decode(uris[0]) == (run_dir / "figures" / f"{FULL_STEMS[0]}.png").read_bytes()
    assert all(f'id="{s}"' in text for s in FULL_STEMS)


def test_report_tables_come_from_trials_parquet(run_dir):
    """Counts and the p50 of e_rho in the report equal an independent computation on trials.parquet."""
    text = (run_dir / "report.html").read_text()
    t = pd.read_parquet(run_dir / "trials.parquet")
    for label in ("iekf", "ekf"):
        g = t[t["filter"] == label]
        nl, ni = int(g["lost"].sum()), int(g["inconsistent"].sum())
        assert f"{len(g) - nl} of {len(g)} trials in the statistics; {nl} lost, {ni} inconsistent" in text
    v = np.sort(t.loc[(t["filter"] == "iekf") & ~t["lost"], "e_rho"].to_numpy())
    p50 = v[int(np.ceil(0.5 * v.size)) - 1]  # inverted CDF: smallest value with F >= 0.5
    assert f'<td class="l">50</td><td>{p50:.3g}</td>' in text
    # the scenario summary and run facts
    assert "time.duration_s</td><td class=\"l\">20</td>" in text
    assert "state_dim</td><td class=\"l\">30</td>" in text


def test_thesis_table_beside_ours_for_a_caseB_run(run_dir):
    """The run is named caseB-small: the thesis's Table 6.2 and the ratio ours/thesis are shown."""
    text = (run_dir / "report.html").read_text()
    th = thesis_percentiles("B")
    assert "thesis Table 6.2: case B, IEKF, 100 trials" in text
    side = text.split("thesis Table 6.2")[1].split("</table>")[0]
    row50 = re.search(r'<td class="l">50</td>((?:<td>[^<]*</td>){6})', side).group(1)
    assert [float(x) for x in re.findall(r"<td>([^<]*)</td>", row50)] == pytest.approx(th.iloc[0, 2:].to_numpy(float))
    ours = pd.read_csv(run_dir / "percentiles.csv")
    o = ours[(ours["filter"] == "iekf") & (ours["population"] == "converged") & (ours["percentile"] == 90)]
    ratio = float(o["e_theta"].iloc[0]) / float(th.loc[th["percentile"] == 90, "e_theta"].iloc[0])
    ratio_table = text.split("ratio this run / thesis")[1].split("</table>")[0]
    row90 = re.search(r'<td class="l">90</td>((?:<td>[^<]*</td>){6})', ratio_table).group(1)
    assert f"<td>{ratio:.3g}</td>" == re.findall(r"<td>[^<]*</td>", row90)[3]


@pytest.mark.parametrize("name,case", [("caseA", "A"), ("caseF-ci", "F"), ("caseB.small", "B"), ("caseG", None),
                                       ("mycaseB", None), ("caseBx", None), ("casea", None)])  # fmt: skip
def test_thesis_case_names(name, case):
    assert thesis_case(name) == case


def test_no_thesis_table_for_other_scenarios(run_dir):
    data = rep.load_run(run_dir)
    data.config["name"] = "my-orbit"
    text = rep.render_report(data, figs.FigureSet())
    assert "thesis Table" not in text
    data.config["name"] = "caseD-long"
    assert "thesis Table 6.4: case D" in rep.render_report(data, figs.FigureSet())


# --------------------------------------------------------------------------- folders and missing inputs


def test_report_on_a_folder_writes_each_report_and_an_index(run_dir, tmp_path):
    """One full run, one without time series / timing / EKF: both reported, the second skips with notes."""
    folder = tmp_path / "runs"
    full = copy_run(run_dir, folder / "full")
    lean = copy_run(run_dir, folder / "nested" / "lean", drop=("timeseries.parquet", "timing.parquet"))
    t = pd.read_parquet(lean / "trials.parquet")
    t[t["filter"] == "iekf"].to_parquet(lean / "trials.parquet")
    (folder / "notes").mkdir()
    (folder / "notes" / "readme.txt").write_text("not a run")
    r = spmc("report", folder)
    assert r.exit_code == 0, r.output
    printed = r.output.split()
    assert str(full / "report.html") in printed and str(lean / "report.html") in printed
    assert str(folder / "index.html") in printed
    for stem in FULL_STEMS:
        assert (full / "figures" / f"{stem}.png").is_file() and (full / "figures" / f"{stem}.svg").is_file()
    lean_figs = sorted(p.stem for p in (lean / "figures").glob("*.png"))
    assert lean_figs == ["hist-iekf"]
    text = (lean / "report.html").read_text()
    assert "no timeseries.parquet" in text and "no timing.parquet" in text
    assert "does not have both an EKF and an IEKF" in text
    index = (folder / "index.html").read_text()
    assert index.count('href="full/report.html"') == 2  # iekf and ekf rows
    assert index.count('href="nested/lean/report.html"') == 1
    assert "notes" not in re.findall(r'href="([^"]+)"', index)
    # index p50 of e_rho for the full run's IEKF, computed independently (the plain EKF's trials
    # of this short case are all marked inconsistent since issue 10, so it has no converged value)
    tf = pd.read_parquet(full / "trials.parquet")
    v = np.sort(tf.loc[(tf["filter"] == "iekf") & ~tf["diverged"], "e_rho"].to_numpy())
    assert v.size
    row = [ln for ln in index.splitlines() if 'href="full/report.html"' in ln and ">iekf<" in ln][0]
    assert f"<td>{v[int(np.ceil(0.5 * v.size)) - 1]:.3g}</td>" in row


def test_partial_run_directory_is_a_clear_error_listing_what_is_missing(run_dir, tmp_path):
    bad = copy_run(run_dir, tmp_path / "bad", drop=("config.yaml", "trials.parquet"))
    (bad / "timeseries.parquet").write_bytes(b"not parquet")
    with pytest.raises(rep.ReportError) as ei:
        rep.build_run_report(bad)
    probs = ei.value.problems
    assert "missing config.yaml" in probs and "missing trials.parquet" in probs
    assert any(p.startswith("timeseries.parquet is unreadable") for p in probs)
    r = spmc("report", bad)
    assert r.exit_code == 2
    for needle in ("missing config.yaml", "missing trials.parquet", "timeseries.parquet is unreadable"):
        assert needle in r.output
    assert not (bad / "report.html").exists() and not (bad / "figures").exists()


def test_not_a_run_directory(tmp_path):
    sim = tmp_path / "sim"
    sim.mkdir()
    (sim / "manifest.json").write_text('{"kind": "simulate"}')
    r = spmc("report", sim)
    assert r.exit_code == 2 and "kind 'simulate'" in r.output
    empty = tmp_path / "empty"
    empty.mkdir()
    r = spmc("report", empty)
    assert r.exit_code == 2 and "no run directories" in r.output
    r = spmc("report", tmp_path / "nope")
    assert r.exit_code == 2 and "no such directory" in r.output


def test_trials_parquet_without_error_columns(run_dir, tmp_path):
    d = copy_run(run_dir, tmp_path / "d", drop=("timeseries.parquet",))
    pd.read_parquet(d / "trials.parquet").drop(columns=["e_k1", "e_k2"]).to_parquet(d / "trials.parquet")
    with pytest.raises(rep.ReportError, match="lacks columns e_k1, e_k2"):
        rep.load_run(d)


# --------------------------------------------------------------------------- the statistics behind the figures


def trials_table(rows):
    """rows: (trial, filter, diverged, e) with the same e for the six errors."""
    d = [{"trial": t, "filter": f, "diverged": dv, **{n: e for n in ERROR_NAMES}} for t, f, dv, e in rows]
    return pd.DataFrame(d)


def test_paired_differences_keep_only_trials_where_both_converged():
    t = trials_table([(0, "ekf", False, 3.0), (0, "iekf", False, 1.0),
                      (1, "ekf", True, np.nan), (1, "iekf", False, 2.0),
                      (2, "ekf", False, 5.0), (2, "iekf", True, np.nan),
                      (3, "ekf", False, 1.5), (3, "iekf", False, 2.0),
                      (4, "iekf", False, 9.0)])  # fmt: skip
    diff, n_common = figs.paired_differences(t, "ekf", "iekf")
    assert n_common == 4  # trial 4 has no EKF row
    assert diff["trial"].tolist() == [0, 3]
    assert diff["e_theta"].tolist() == [2.0, -0.5]


def test_axis_error_figure_draws_each_trials_errors_as_one_collection_per_axis(run_dir, monkeypatch):
    """The per-axis figure: in each panel one line collection holding the first ``MAX_LINES`` trials' errors against
    time (a lost trial's NaN tail is not drawn), whatever the number of trials."""
    from matplotlib.collections import LineCollection

    ts = pd.read_parquet(run_dir / "timeseries.parquet")
    g = ts[ts["filter"] == "iekf"].copy()
    g.loc[(g["trial"] == 1) & (g["step"] >= 10), [c for c in g.columns if c.startswith("err_")]] = np.nan
    monkeypatch.setattr(figs, "MAX_LINES", 4)
    fig = figs.axis_error_figure(g, "iekf", 5.0)
    panels = [ax for ax in fig.axes if ax.get_visible()]
    assert len(panels) == len(figs.AXES) == 14
    for ax, c in zip(panels, figs.AXES):
        (lc,) = [a for a in ax.collections if isinstance(a, LineCollection)]
        segs = lc.get_segments()
        assert len(segs) == 4  # trials 0-3 of the 6
        for trial, seg in enumerate(segs):
            rows = g[g["trial"] == trial].sort_values("step")
            rows = rows[np.isfinite(rows[f"err_{c}"])]  # (the collection's paths leave NaN points out)
            assert len(rows) == (10 if trial == 1 else 21)
            np.testing.assert_array_equal(seg, rows[["t", f"err_{c}"]].to_numpy())


def test_ekf_iekf_pair_by_label_then_by_type():
    assert figs.ekf_iekf_pair(["iekf", "ekf"], {}) == ("ekf", "iekf")
    assert figs.ekf_iekf_pair(["a", "b"], {"a": "iekf", "b": "ekf"}) == ("b", "a")
    assert figs.ekf_iekf_pair(["a", "b", "c"], {"a": "iekf", "b": "ekf", "c": "ekf"}) is None
    assert figs.ekf_iekf_pair(["a"], {"a": "iekf"}) is None


def test_mean_band_matches_chi2_and_its_normal_limit():
    from scipy.stats import chi2

    lo, hi = figs.mean_band(np.array([1]), np.array([30]))
    assert (lo[0], hi[0]) == pytest.approx(chi2.ppf([0.025, 0.975], 30))
    # large M: the mean of M chi2(n) is ~ N(n, 2n/M)
    M, n = 4000, 30
    lo, hi = figs.mean_band(np.array([M]), np.array([n]))
    half = 1.959964 * np.sqrt(2 * n / M)
    assert lo[0] == pytest.approx(n - half, rel=2e-3) and hi[0] == pytest.approx(n + half, rel=2e-3)
    lo, hi = figs.mean_band(np.array([0, 5]), np.array([30, 0]))
    assert np.isnan(lo).all() and np.isnan(hi).all()


def test_mean_band_covers_95_percent_of_simulated_means():
    rng = np.random.default_rng(7)
    M, n = 20, 13
    means = rng.chisquare(n, size=(40000, M)).mean(axis=1)
    lo, hi = figs.mean_band(np.array([M]), np.array([n]))
    inside = np.mean((means >= lo[0]) & (means <= hi[0]))
    assert inside == pytest.approx(0.95, abs=0.005)


def test_consistency_mean_over_alive_trials_and_per_step_dof():
    # 3 trials, 3 steps; trial 2 diverged after step 0 (NaN afterwards); NIS dof 0 at step 0, then 4 and 6
    rows = []
    nees = {0: [1.0, 2.0, 3.0], 1: [4.0, 6.0, np.nan], 2: [10.0, 20.0, np.nan]}
    nis = {0: [np.nan] * 3, 1: [1.0, 3.0, np.nan], 2: [5.0, 7.0, np.nan]}
    dof = {0: 0, 1: 4, 2: 6}
    for k in range(3):
        for i in range(3):
            rows.append({"trial": i, "filter": "f", "step": k, "t": 2.0 * k, "nees": nees[k][i], "nis": nis[k][i],
                         "nis_dof": dof[k]})  # fmt: skip
    ts = pd.DataFrame(rows).sample(frac=1.0, random_state=1)  # order must not matter
    c = figs.consistency(ts, "f", "nees", 30)
    assert c.t.tolist() == [0.0, 2.0, 4.0]
    assert c.M.tolist() == [3, 2, 2]
    assert c.mean == pytest.approx([2.0, 5.0, 15.0])
    from scipy.stats import chi2

    assert c.lo[1] == pytest.approx(chi2.ppf(0.025, 60) / 2) and c.hi[0] == pytest.approx(chi2.ppf(0.975, 90) / 3)
    # NIS per dimension: sum(nis) / sum(nis_dof) over the live trials, band chi2.ppf(., D) / D with D = sum(nis_dof)
    c = figs.consistency(ts, "f", "nis", None)
    assert c.M.tolist() == [0, 2, 2] and np.isnan(c.mean[0]) and np.isnan(c.lo[0])
    assert c.mean[1:] == pytest.approx([4.0 / 8, 12.0 / 12])
    assert c.dof[1:].tolist() == [1.0, 1.0]
    assert c.lo[1] == pytest.approx(chi2.ppf(0.025, 8) / 8) and c.hi[2] == pytest.approx(chi2.ppf(0.975, 12) / 12)
    assert c.inside == (int(np.sum([(0.5 >= c.lo[1]) & (0.5 <= c.hi[1]), (1.0 >= c.lo[2]) & (1.0 <= c.hi[2])])), 2)


def test_time_percentiles_ignore_diverged_trials():
    A = np.array([[1.0, 1.0], [2.0, np.nan], [3.0, 3.0], [4.0, np.nan], [5.0, 5.0]])
    q = figs.time_percentiles(A, [0, 50, 100])
    assert q[:, 0].tolist() == [1.0, 3.0, 5.0]
    assert q[:, 1].tolist() == [1.0, 3.0, 5.0]


def test_compute_time_table():
    timing = pd.DataFrame({"trial": [0, 1, 2, 0, 1, 2], "filter": ["a"] * 3 + ["b"] * 3,
                           "runtime_s": [1.0, 2.0, 6.0, 0.5, 0.5, 0.5], "chunk": 0})  # fmt: skip
    ct = figs.compute_time_table(timing)
    assert ct.to_dict("records") == [
        {"filter": "a", "trials": 3, "max_s": 6.0, "mean_s": 3.0, "min_s": 1.0},
        {"filter": "b", "trials": 3, "max_s": 0.5, "mean_s": 0.5, "min_s": 0.5},
    ]


def test_divergence_reasons_grouped_without_numbers(run_dir, tmp_path):
    d = copy_run(run_dir, tmp_path / "d", drop=("timeseries.parquet",))
    t = pd.read_parquet(d / "trials.parquet")
    for flag in ("lost", "inconsistent"):  # only the ones injected below
        t[flag], t[f"{flag}_step"], t[f"{flag}_reason"] = False, -1, ""
    sel = (t["filter"] == "ekf") & t["trial"].isin([1, 4])
    t.loc[sel, "inconsistent"] = True
    t.loc[sel, "inconsistent_step"] = [3, 5]
    t.loc[sel, "inconsistent_reason"] = ["inconsistent: error bound exceeded: e_rho = 1.2e+03 > 1000",
                                         "inconsistent: error bound exceeded: e_rho = 2e+03 > 1000"]  # fmt: skip
    sel = (t["filter"] == "iekf") & t["trial"].isin([0, 2, 3])
    t.loc[sel, "lost"] = True
    t.loc[sel, "lost_step"] = [12, 14, 19]
    t.loc[sel, "lost_reason"] = ["filter lost: mean NIS over 10 steps = 300 x its dimension > 100",
                                 "filter lost: mean NIS over 10 steps = 1.2e+03 x its dimension > 100",
                                 "covariance not positive definite"]  # fmt: skip
    t.to_parquet(d / "trials.parquet")
    rows = rep.divergence_rows(rep.load_run(d))
    assert rows == [["iekf", "lost", "filter lost: mean NIS", "2", "0, 2", "13", "13"],
                    ["iekf", "lost", "covariance not positive definite", "1", "3", "19", "19"],
                    ["ekf", "inconsistent (flag)", "inconsistent: error bound exceeded: e_rho", "2", "1, 4", "4", "4"]]
    shutil.rmtree(d)
