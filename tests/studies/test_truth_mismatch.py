"""``studies.truth_mismatch`` and its part of ``spmc dynamics``."""

from __future__ import annotations

import numpy as np
import pandas as pd
import yaml
from scenarios import scenario_dict, write_scenario
from typer.testing import CliRunner

import stereopose_mc.cli.dynamics_cmd  # noqa: F401  (registers the command)
import stereopose_mc.cli.main  # noqa: F401
from stereopose_mc.cli.app import app
from stereopose_mc.config import load_scenario_text
from stereopose_mc.config.resolve import setup_of
from stereopose_mc.studies.truth_mismatch import mismatch_frame, mismatch_study

TIME = {"dt_s": 2.0, "duration_s": 60.0, "error_window_start_s": 2.0}


def setup_with(tm):
    return setup_of(load_scenario_text(yaml.safe_dump(scenario_dict(time=TIME, truth_model=tm))))


def test_effects_and_their_signatures():
    df = mismatch_frame(mismatch_study(setup_with({"j2": True, "gravity_gradient_torque": True})))
    r = df.set_index("effect")
    assert list(r.index) == ["j2", "gravity_gradient", "all"]
    # a torque moves the attitude only; J2 moves the target relative to the leader
    assert r.loc["gravity_gradient", "drift_rho_max_m"] < 1e-6 < r.loc["j2", "drift_rho_max_m"]
    assert r.loc["gravity_gradient", "drift_theta_max_deg"] > 10 * r.loc["j2", "drift_theta_max_deg"]
    assert (r.loc["all"] > 0).all()


def test_without_perturbations_the_filters_model_is_the_truth():
    # inertial propagation with nothing added, converted to LVLH, against the filters' Keplerian model
    # restarted each step from the osculating orbit: only the RK4 error (20 substeps) remains
    ms = mismatch_study(setup_with({}))
    assert len(ms) == 1 and ms[0].effect == "all"
    assert ms[0].step_rho.max() < 1e-8 and ms[0].step_omega.max() < 1e-12 and ms[0].drift_rho.max() < 1e-6


def test_spmc_dynamics_reports_the_mismatch(tmp_path):
    scn = write_scenario(tmp_path / "s.yaml", time=TIME, truth_model={"gravity_gradient_torque": True})
    out = tmp_path / "dyn"
    res = CliRunner().invoke(app, ["dynamics", str(scn), "--out", str(out), "--horizon", "60",
                                   "--timing-points", "1", "--repeats", "1"])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "(d) truth_model gravity_gradient" in res.output
    df = pd.read_csv(out / "truth_mismatch.csv")
    assert list(df["effect"]) == ["gravity_gradient"] and np.isfinite(df.drop(columns="effect").to_numpy()).all()
    assert (out / "truth_mismatch.png").read_bytes()[:4] == b"\x89PNG"
    assert "| gravity_gradient |" in (out / "truth_mismatch.md").read_text()
