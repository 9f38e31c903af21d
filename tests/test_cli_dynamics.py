"""``spmc dynamics``: writes every listed output and refuses a non-empty output directory."""

from __future__ import annotations

import pandas as pd
import pytest
from scenarios import write_scenario
from typer.testing import CliRunner

import stereopose_mc.cli.dynamics_cmd  # noqa: F401  (registers the command)
import stereopose_mc.cli.main  # noqa: F401
from stereopose_mc.cli.app import app

STEMS = ("cw_circular", "cw_eccentric", "cw_difference", "cw_docking", "features", "feature_deviation",
         "coupled_vs_simplified", "timing")
ARGS = ["--horizon", "120", "--timing-points", "1,3", "--repeats", "1"]


def test_dynamics_writes_all_outputs_and_refuses_non_empty_dir(tmp_path):
    scn = write_scenario(tmp_path / "s.yaml", time={"dt_s": 1.0, "duration_s": 10.0, "error_window_start_s": 2.0})
    out = tmp_path / "dyn"
    runner = CliRunner()
    res = runner.invoke(app, ["dynamics", str(scn), "--out", str(out), *ARGS])
    assert res.exit_code == 0, res.output
    assert "(a)" in res.output and "(b)" in res.output and "(c)" in res.output
    names = {p.name for p in out.iterdir()}
    expected = {f"{s}.{e}" for s in STEMS for e in ("png", "svg")} | {
        "dynamics.csv", "dynamics.md", "timing.csv", "manifest.json"
    }
    assert expected <= names
    png = (out / "timing.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "cw_circular.svg").read_text().lstrip().startswith("<?xml")

    summary = pd.read_csv(out / "dynamics.csv")
    q = summary.set_index(["study", "case", "quantity"])["value"]
    # (a) within 120 s the CW error is tiny on the circular orbit, larger on the eccentric one
    circ = q[("nl_vs_cw", "circular", "max_position_difference")]
    ecc = q[("nl_vs_cw", "eccentric", "max_position_difference")]
    assert 0.0 < circ < ecc
    assert q[("nl_vs_cw_scaling", "circular", "loglog_slope")] == pytest.approx(2.0, abs=0.01)
    # (b) coupled and simplified agree far below the feature lever arm (1.5 m)
    assert q[("coupled_vs_simplified", "all_points", "max_feature_difference")] < 1e-8
    # (c) state sizes 13+3N and 13+9N, timings positive
    timing = pd.read_csv(out / "timing.csv")
    assert list(timing.N) == [1, 3]
    assert list(timing.n_simplified) == [16, 22] and list(timing.n_coupled) == [22, 40]
    clocks = [c for c in timing.columns if c.startswith(("t_", "cpu_"))]
    assert len(clocks) == 8 and (timing[clocks].to_numpy() > 0).all()
    assert set(timing.columns) >= {"v_rk4_pct", "v_dop853_pct", "nfev_dop853_simplified", "nfev_dop853_coupled"}
    md = (out / "dynamics.md").read_text()
    assert "## (a)" in md and "## (b)" in md and "## (c)" in md

    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    res2 = runner.invoke(app, ["dynamics", str(scn), "--out", str(out), *ARGS])
    assert res2.exit_code == 2
    assert "not empty" in res2.output
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before


def test_dynamics_rejects_bad_options(tmp_path):
    scn = write_scenario(tmp_path / "s.yaml")
    out = tmp_path / "dyn"
    args = ["dynamics", str(scn), "--out", str(out), "--timing-points", "1,x", "--horizon", "-5"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2
    assert "--timing-points" in res.output and "--horizon" in res.output
    assert not out.exists()

