"""``spmc sweep``: a 2x3 grid of short campaigns, its report, resume, compare and errors."""

from __future__ import annotations

import json

import pandas as pd
import pytest
from scenarios import write_scenario
from typer.testing import CliRunner

from stereopose_mc.cli.main import app
from stereopose_mc.studies import sweep as sw

SETS = ["--set", "camera.baseline_m=0.5,1.0", "--set", "truth_initial_state.rho_m[1]=30,45,60"]


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    root = tmp_path_factory.mktemp("sweep")
    cfg = write_scenario(root / "s.yaml", time={"dt_s": 1.0, "duration_s": 12.0, "error_window_start_s": 4.0},
                         filters=[{"type": "ekf"}])  # fmt: skip
    r = CliRunner().invoke(app, ["sweep", str(cfg), *SETS, "--trials", "3", "--out", str(root / "out"), "-q",
                                 "--timeseries", "none", "--no-report"])  # fmt: skip
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(app, ["report", str(root / "out")])  # the sweep report, as `spmc sweep` writes it
    assert r.exit_code == 0 and "report.html" in r.output, r.output
    return root, cfg


def test_grid_runs_every_point_as_a_run_directory(grid):
    root, _ = grid
    spec = json.loads((root / "out" / "sweep.json").read_text())
    assert len(spec["points"]) == 6
    values = [(p["values"]["camera.baseline_m"], p["values"]["truth_initial_state.rho_m[1]"]) for p in spec["points"]]
    assert values == [(0.5, 30), (0.5, 45), (0.5, 60), (1.0, 30), (1.0, 45), (1.0, 60)]
    for p in spec["points"]:
        cfg = (root / "out" / p["name"] / "config.yaml").read_text()
        assert f"baseline_m: {p['values']['camera.baseline_m']}" in cfg
    s = pd.read_csv(root / "out" / "sweep.csv")
    assert len(s) == 6 and {"divergence_rate", "e_rho_p50", "e_rho_p10", "e_rho_p90"} <= set(s.columns)
    assert (s["trials"] == 3).all()
    html = (root / "out" / "report.html").read_text()
    assert "against camera.baseline_m" in html and "against truth_initial_state.rho_m[1]" in html
    assert (root / "out" / "index.html").is_file()


def test_rerun_resumes_and_compare_works_on_sweeps(grid):
    root, cfg = grid
    r = CliRunner().invoke(app, ["sweep", str(cfg), *SETS, "--trials", "3", "--out", str(root / "out"), "--no-report",
                                 "--timeseries", "none"])  # fmt: skip
    assert r.exit_code == 0 and r.output.count("finished, skipped") == 6
    r = CliRunner().invoke(app, ["compare", str(root / "out"), str(root / "out" / "percentiles.csv")])
    assert r.exit_code == 0 and "**OK**" in r.output


def test_sweep_errors_exit_2(grid, tmp_path):
    _, cfg = grid
    r = CliRunner().invoke(app, ["sweep", str(cfg), "--set", "camera.baseline_m=0.5,-1", "--out", str(tmp_path / "a")])
    assert r.exit_code == 2 and "camera.baseline_m=-1" in r.output and "greater than 0" in r.output
    r = CliRunner().invoke(app, ["sweep", str(cfg), *SETS, "--zip", "--out", str(tmp_path / "b")])
    assert r.exit_code == 2 and "same length" in r.output
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_zip_pairs_values():
    axes = [sw.Axis("a", [1, 2]), sw.Axis("b", [3, 4])]
    assert sw.points_of(axes, True) == [(1, 3), (2, 4)]
    assert sw.parse_set("x.y=[1,2],[3,4]").values == [[1, 2], [3, 4]]


def test_bundled_sweep_file_expands_to_valid_points():
    from scenarios import CONFIGS

    f = CONFIGS / "sweeps" / "baseline-range.yaml"
    assert sw.is_sweep_file(f) and not sw.is_sweep_file(CONFIGS / "caseB.yaml")
    scenario, sets, zipped, trials = sw.load_sweep_file(f)
    axes, points = sw.build_points(scenario, sets, zipped, trials)
    assert [a.path for a in axes] == ["camera.baseline_m", "truth_initial_state.rho_m[1]"] and len(points) == 9
    p = points[-1].scenario
    assert p.camera.baseline_m == 2.0 and p.truth_initial_state.rho_m == [10.0, 120.0, 10.0] and p.trials == 50


def test_validate_checks_every_point_of_a_sweep_file(tmp_path):
    from scenarios import CONFIGS

    r = CliRunner().invoke(app, ["validate", str(CONFIGS / "sweeps" / "baseline-range.yaml")])
    assert r.exit_code == 0 and r.output.startswith("ok:")
    bad = tmp_path / "bad.yaml"
    bad.write_text(f"sweep:\n  scenario: {CONFIGS / 'caseB.yaml'}\n  set: {{camera.baseline_m: [1.0, 0.0]}}\n")
    r = CliRunner().invoke(app, ["validate", str(bad)])
    assert r.exit_code == 2 and "camera.baseline_m=0.0" in r.output


def test_sweep_points_run_the_compiled_kernels_by_default_and_numpy_on_request(grid, tmp_path):
    root, cfg = grid
    for p in json.loads((root / "out" / "sweep.json").read_text())["points"]:
        assert json.loads((root / "out" / p["name"] / "manifest.json").read_text())["backend"]["kernels"] == "compiled"
    r = CliRunner().invoke(app, ["sweep", str(cfg), "--set", "camera.baseline_m=0.5", "--trials", "2", "--out",
                                 str(tmp_path / "np"), "-q", "--timeseries", "none", "--no-report",
                                 "--kernels", "numpy"])  # fmt: skip
    assert r.exit_code == 0, r.output
    (point,) = json.loads((tmp_path / "np" / "sweep.json").read_text())["points"]
    assert json.loads((tmp_path / "np" / point["name"] / "manifest.json").read_text())["backend"]["kernels"] == "numpy"


def test_each_point_after_the_first_says_the_sweeps_time_and_the_rest_at_that_pace(grid, tmp_path):
    _, cfg = grid
    r = CliRunner().invoke(app, ["sweep", str(cfg), "--set", "camera.baseline_m=0.5,1.0,2.0", "--trials", "2",
                                 "--out", str(tmp_path / "eta"), "--no-report", "--timeseries", "none"])  # fmt: skip
    assert r.exit_code == 0, r.output
    lines = [ln for ln in r.output.splitlines() if ln.startswith("[")]
    assert [ln.split("]")[0] for ln in lines] == ["[1/3", "[2/3", "[3/3"]
    assert lines[0].endswith(": running")  # nothing measured yet
    assert "; sweep: " in lines[1] and " elapsed, about " in lines[1] and lines[1].endswith(" left")
    assert "; sweep: " in lines[2] and " elapsed, about " in lines[2]
