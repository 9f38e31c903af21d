"""Dispersed campaigns through the engine: determinism, rerun, columns, invalid draws, validation."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
import yaml
from scenarios import scenario_dict
from typer.testing import CliRunner

from stereopose_mc.cli.main import app
from stereopose_mc.config import load_scenario_text
from stereopose_mc.mc import engine
from stereopose_mc.mc.rerun import rerun_trial

DISP = {
    "truth_initial_state.rho_m": {"dist": "normal", "std": [1.0, 3.0, 1.0]},
    "truth_initial_state.omega_degps": {"dist": "uniform", "low": -0.3, "high": 0.3},
    "target.inertia_kgm2": {"dist": "uniform", "low": [0.8, 0.9, 1.0], "high": [1.0, 1.1, 1.3], "mode": "replace"},
    "leader.orbit.a_km": {"dist": "normal", "std": 350.0, "applies_to": "both"},  # some draws are invalid
    "camera.baseline_m": {"dist": "normal", "std": 0.01},
}


def text(**over) -> str:
    d = scenario_dict("caseB", time={"dt_s": 1.0, "duration_s": 15.0, "error_window_start_s": 5.0}, trials=12, **over)
    d["dispersions"] = DISP
    return yaml.safe_dump(d, sort_keys=False)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    scn = load_scenario_text(text(), "<test>")
    root = tmp_path_factory.mktemp("disp")
    a = engine.run(scn, root / "a", engine.RunOptions(jobs=1, chunk_size=8, command=["test"]))
    b = engine.run(scn, root / "b", engine.RunOptions(jobs=2, chunk_size=3, command=["test"]))
    return root, a, b


def test_dispersed_run_is_byte_identical_across_jobs_and_chunks(runs):
    root, _, _ = runs
    for name in ("trials.parquet", "timeseries.parquet", "percentiles.csv"):
        assert (root / "a" / name).read_bytes() == (root / "b" / name).read_bytes(), name


def test_columns_units_and_invalid_trials(runs):
    root, a, _ = runs
    df = pd.read_parquet(root / "a" / "trials.parquet")
    assert {"truth_initial_state.rho_m[1]", "target.inertia_kgm2[2]", "leader.orbit.a_km", "invalid"} <= set(df)
    unit = {f.name: (f.metadata or {}).get(b"unit") for f in pq.read_schema(root / "a" / "trials.parquet")}
    assert unit["truth_initial_state.omega_degps[0]"] == b"deg/s" and unit["leader.orbit.a_km"] == b"km"
    bad = df["leader.orbit.a_km"] * (1 - 0.05) < 6378.137
    assert bad.any() and (~bad).any()  # the seed gives both kinds
    assert (df["invalid"] == bad).all()
    assert df.loc[bad, "diverged"].all() and (df.loc[bad, "diverged_step"] == 0).all()
    assert df.loc[bad, "diverged_reason"].str.startswith("invalid draw: leader.orbit").all()
    assert df.loc[~bad, "e_rho"].notna().any()


def test_rerun_reproduces_a_dispersed_trial(runs):
    root, _, _ = runs
    df = pd.read_parquet(root / "a" / "trials.parquet")
    j = int(df.loc[~df["invalid"], "trial"].iloc[-1])
    res = rerun_trial(root / "a", j)
    assert res.identical


def test_simulate_trial_writes_the_dispersed_truth(runs, tmp_path):
    root, _, _ = runs
    df = pd.read_parquet(root / "a" / "trials.parquet")
    j = int(df.loc[~df["invalid"], "trial"].iloc[0])
    cfg = tmp_path / "s.yaml"
    cfg.write_text(text())
    r = CliRunner().invoke(app, ["simulate", str(cfg), "--trial", str(j), "--out", str(tmp_path / "sim")])
    assert r.exit_code == 0, r.output
    truth = pd.read_parquet(tmp_path / "sim" / "truth.parquet")
    row = df[df["trial"] == j].iloc[0]
    assert truth["rho_y"].iloc[0] == row["truth_initial_state.rho_m[1]"]


def test_bad_dispersions_are_rejected_with_file_line_and_exit_2(tmp_path):
    d = yaml.safe_load(text())
    d["dispersions"] = {"sampling": "random",
                        "truth_initial_state.rho": {"dist": "normal", "std": 1.0},
                        "target.inertia_kgm2": {"dist": "uniform", "low": [0.1, 0.9, 1.0], "high": [1.0, 1.1, 1.3],
                                                "mode": "replace"}}  # fmt: skip
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(yaml.safe_dump(d, sort_keys=False))
    lines = cfg.read_text().splitlines()
    r = CliRunner().invoke(app, ["validate", str(cfg)])
    assert r.exit_code == 2
    err = r.output.splitlines()
    line_rho = 1 + next(i for i, s in enumerate(lines) if "truth_initial_state.rho:" in s)
    assert any(f"bad.yaml:{line_rho}: dispersions.truth_initial_state.rho: unknown" in e and "rho_m" in e for e in err)
    assert any("dispersions.target.inertia_kgm2: can produce an invalid scenario" in e and "triangle" in e for e in err)


def test_report_of_a_dispersed_run_has_the_sensitivity_section_drawn_by_one_or_two_processes(runs, tmp_path):
    """A dispersed run's report has the sensitivity section (its table and figures). Its figures are drawn in the
    report's batch (``figures.drawn_files``): told to the progress line after the run's own figures, byte for byte
    the same with 2 processes as with 1; the scatter's caption counts the pairs it draws (at most
    ``TOP_SCATTER``)."""
    import shutil

    from stereopose_mc.outputs import sensitivity_report
    from stereopose_mc.outputs.report import build_run_report

    root, _, _ = runs
    told, html = {}, {}
    for jobs in (1, 2):
        d = tmp_path / f"j{jobs}"
        shutil.copytree(root / "a", d)
        told[jobs] = []
        html[jobs] = build_run_report(d, told[jobs].append, jobs=jobs).read_text()
    assert "Sensitivity: what drives the error" in html[1] and "the three strongest drivers" in html[1]
    table = pd.read_csv(tmp_path / "j1" / "sensitivity.csv")
    assert {"e_rho", "diverged"} & set(table["metric"]) and "camera.baseline_m" in set(table["parameter"])
    assert (tmp_path / "j1" / "figures" / "sensitivity-heatmap-iekf.png").is_file()
    sens_keys = [k for k in told[1] if k.startswith("sensitivity-")]
    assert sens_keys == [f"sensitivity-{kind}-{f}" for f in ("iekf", "ekf") for kind in ("heatmap", "scatter")]
    assert told[1] == told[2] and told[1][-4:] == sens_keys
    for key in sens_keys:
        for ext in ("png", "svg"):
            assert (tmp_path / "j1" / "figures" / f"{key}.{ext}").read_bytes() == \
                (tmp_path / "j2" / "figures" / f"{key}.{ext}").read_bytes()  # fmt: skip
    pairs = int(((table["filter"] == "iekf") & (table["statistic"] == "spearman")).sum())
    n = min(pairs, sensitivity_report.TOP_SCATTER)
    assert 0 < n and f"The {n} (metric, scalar) pairs with the largest |rho|." in html[1]


def _chunk(disp: dict, baseline: float = 1.0):
    from stereopose_mc.mc import dispersed

    d = scenario_dict("caseB", time={"dt_s": 1.0, "duration_s": 6.0, "error_window_start_s": 2.0}, trials=3,
                      camera={"baseline_m": baseline})  # fmt: skip
    d["dispersions"] = disp
    scn = load_scenario_text(yaml.safe_dump(d, sort_keys=False), "<test>")
    p = engine.prepare(scn)
    res, _ = dispersed.run_chunk(scn, [0, 1, 2], p.setup, p.bounds)
    return res.runs[0].errors


def test_applies_to_selects_what_the_filter_model_sees():
    """A baseline of 1.2 m: dispersed with applies_to both == nominal 1.2 m; truth-only differs."""
    import numpy as np

    inert = {"leader.orbit.raan_deg": {"dist": "choice", "values": [0.0]}}  # no effect on the dynamics
    both = _chunk({**inert, "camera.baseline_m": {"dist": "choice", "values": [1.2], "applies_to": "both"}})
    nominal = _chunk(inert, baseline=1.2)
    truth_only = _chunk({**inert, "camera.baseline_m": {"dist": "choice", "values": [1.2]}})
    assert np.array_equal(both, nominal, equal_nan=True)
    assert not np.allclose(truth_only[:, 1:], nominal[:, 1:], equal_nan=True)


def test_applies_to_centres_the_initial_estimate():
    """State keys: both -> initial error is the N(0, P0) draw alone (as without dispersion); truth -> plus the offset."""
    import numpy as np

    inert = {"leader.orbit.raan_deg": {"dist": "choice", "values": [0.0]}}
    shift = {"dist": "choice", "values": [[3.0, 4.0, 0.0]]}  # |offset| = 5 m
    nominal = _chunk(inert)[:, 0, 0]
    both = _chunk({**inert, "truth_initial_state.rho_m": {**shift, "mode": "add", "applies_to": "both"}})[:, 0, 0]
    truth = _chunk({**inert, "truth_initial_state.rho_m": {**shift, "mode": "add"}})[:, 0, 0]
    assert np.allclose(both, nominal, rtol=1e-12)
    assert np.all(np.abs(truth - 5.0) <= nominal + 1e-9) and not np.allclose(truth, nominal)


def faulty_text() -> str:
    """A dispersed campaign with tracker faults and a gated filter (issues 11 and 12 together)."""
    d = yaml.safe_load(text())
    d["measurements"]["dropout_probability"] = 0.1
    d["measurements"]["outliers"] = {"probability": 0.05, "model": "uniform_image"}
    for f in d["filters"]:
        f["gating"] = {"probability": 0.999}
    return yaml.safe_dump(d, sort_keys=False)


def test_dispersed_faults_and_gating_are_chunk_independent_and_counted(tmp_path):
    scn = load_scenario_text(faulty_text(), "<test>")
    a = tmp_path / "a"
    b = tmp_path / "b"
    engine.run(scn, a, engine.RunOptions(jobs=1, chunk_size=12, command=["test"]))
    engine.run(scn, b, engine.RunOptions(jobs=1, chunk_size=5, command=["test"]))
    for name in ("trials.parquet", "timeseries.parquet"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    df = pd.read_parquet(a / "trials.parquet")
    ok = ~df["invalid"]
    # 10 % dropouts of 5 features over 15 steps: about 7.5 per trial; every valid trial has some
    assert (df.loc[ok, "dropped_features"] > 0).all()
    assert (df.loc[df["invalid"], ["dropped_features", "outlier_features"]] == 0).all().all()
    assert df.loc[ok, "outlier_features"].sum() > 0
    assert df.loc[ok, "gated_features"].sum() >= df.loc[ok, "outlier_features"].sum() // 2


def test_dispersions_with_a_perturbed_truth_are_refused(tmp_path):
    d = yaml.safe_load(text())
    d["truth_model"] = {"j2": True}
    cfg = tmp_path / "j2.yaml"
    cfg.write_text(yaml.safe_dump(d, sort_keys=False))
    r = CliRunner().invoke(app, ["validate", str(cfg)])
    assert r.exit_code == 2
    assert "not supported yet" in r.output and "Traceback" not in r.output


def test_dispersed_campaign_starts_from_measurements_independently_of_chunking(tmp_path):
    d = yaml.safe_load(text())
    d["initial_estimate"] = {"method": "measurements"}
    scn = load_scenario_text(yaml.safe_dump(d, sort_keys=False), "<test>")
    engine.run(scn, tmp_path / "a", engine.RunOptions(jobs=1, chunk_size=12, command=["test"]))
    engine.run(scn, tmp_path / "b", engine.RunOptions(jobs=1, chunk_size=4, command=["test"]))
    assert (tmp_path / "a" / "trials.parquet").read_bytes() == (tmp_path / "b" / "trials.parquet").read_bytes()
    ok = ~pd.read_parquet(tmp_path / "a" / "trials.parquet")["invalid"]
    base = tmp_path / "base"
    engine.run(load_scenario_text(text(), "<test>"), base, engine.RunOptions(jobs=1, chunk_size=12, command=["test"]))
    a = pd.read_parquet(tmp_path / "a" / "timeseries.parquet")
    b = pd.read_parquet(base / "timeseries.parquet")
    # the start differs from the truth-plus-noise start (the measurement start is really used)
    s0a = a[a["step"] == 0].reset_index(drop=True)["e_rho"]
    s0b = b[b["step"] == 0].reset_index(drop=True)["e_rho"]
    assert ok.any() and not np.allclose(s0a.to_numpy(), s0b.to_numpy(), equal_nan=True)


def test_dispersed_runs_have_every_nees_and_its_degrees_of_freedom(runs):
    """Issue 33 item 3: block and gauge-projected NEES finite for every trial not lost (each trial's own truth),
    equal to the window means of the time series, with ``nees_dof = n - 1`` and ``nees_gauge_dof = n - 4``."""
    root, _, _ = runs
    df = pd.read_parquet(root / "a" / "trials.parquet")
    ts = pd.read_parquet(root / "a" / "timeseries.parquet")
    ok = df[~df["lost"]]
    cols = [c for c in df if c.startswith("nees_") and c.endswith("_mean")]
    assert len(cols) == 8 and len(ok) > 0
    assert np.isfinite(ok[cols].to_numpy(float)).all()
    n = 13 + 3 * 5 + 2  # caseB: five feature points
    assert (ok["nees_dof"] == n - 1).all() and (ok["nees_gauge_dof"] == n - 4).all()
    w = ts[(ts["t"] >= 5.0 - 1e-9)].groupby(["trial", "filter"])[["nees_rho", "nees_gauge"]].mean()
    for r in ok.itertuples():
        np.testing.assert_allclose([r.nees_rho_mean, r.nees_gauge_mean], w.loc[(r.trial, r.filter)].to_numpy(),
                                   rtol=1e-12)  # fmt: skip
