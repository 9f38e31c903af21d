"""The report's "Tracker faults and gating" section and the fault columns of the run tables."""

from __future__ import annotations

import pandas as pd
from typer.testing import CliRunner

from stereopose_mc.cli.main import app

from scenarios import scenario_dict, write_scenario


def test_faulty_gated_run_reports_its_counts(tmp_path, run_dir):
    short = {"dt_s": 1.0, "duration_s": 15.0, "error_window_start_s": 5.0}
    m = {**scenario_dict()["measurements"], "dropout_probability": 0.05, "outliers": {"probability": 0.05}}
    scn = write_scenario(tmp_path / "s.yaml", name="faulty", trials=4, time=short, measurements=m,
                         filters=[{"type": "iekf", "gating": {"probability": 0.999}}])  # fmt: skip
    out = tmp_path / "run"
    r = CliRunner().invoke(app, ["run", str(scn), "--out", str(out), "--jobs", "1", "--quiet"])
    assert r.exit_code == 0, r.output
    trials = pd.read_parquet(out / "trials.parquet")
    ts = pd.read_parquet(out / "timeseries.parquet")
    assert (trials["dropped_features"] > 0).any() and (trials["outlier_features"] > 0).any()
    # per-trial totals are the sums of the per-step counts
    per_trial = ts[ts["step"] > 0].groupby("trial")["gated"].sum()
    assert (trials.set_index("trial")["gated_features"] == per_trial).all()
    html = (out / "report.html").read_text(encoding="utf-8")
    assert "Tracker faults and gating" in html
    # an ideal run has no such section
    assert "Tracker faults and gating" not in (run_dir / "report.html").read_text(encoding="utf-8")
