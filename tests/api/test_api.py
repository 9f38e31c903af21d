"""``stereopose_mc.api`` on small runs (case B cut to 13 steps, a few trials)."""

from __future__ import annotations


import pandas as pd
import pyarrow.parquet as pq
import pytest
import yaml

from stereopose_mc import api

from cli_helpers import SHORT
from scenarios import CONFIGS, scenario_dict, write_scenario


@pytest.fixture(scope="module")
def scn():
    return api.from_dict(scenario_dict(trials=3, time=SHORT))


@pytest.fixture(scope="module")
def run3(scn, tmp_path_factory):
    return api.run(scn, out=tmp_path_factory.mktemp("api") / "run")


# ------------------------------------------------------------------------------------------------ scenarios


def test_load_and_from_dict_give_the_same_scenario(tmp_path):
    f = write_scenario(tmp_path / "s.yaml", trials=3, time=SHORT)
    assert api.load(f) == api.from_dict(scenario_dict(trials=3, time=SHORT))
    assert api.load(CONFIGS / "caseB.yaml").name == "caseB"


def test_load_errors_name_file_line_and_key(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text(yaml.safe_dump({**scenario_dict(), "trials": -1}, sort_keys=False))
    with pytest.raises(api.SpmcError) as e:
        api.load(f)
    assert len(e.value.lines) == 1 and e.value.lines[0].startswith(f"{f}:") and "trials:" in e.value.lines[0]


def test_edit_is_the_file_with_the_values_changed(scn):
    d = scenario_dict(trials=3, time=SHORT)
    d["camera"]["baseline_m"] = 0.5
    d["truth_initial_state"]["rho_m"][1] = 60.0
    want = api.from_dict(d)
    assert api.edit(scn, {"camera.baseline_m": 0.5, "truth_initial_state.rho_m[1]": 60}) == want
    assert api.edit(scn, ["camera.baseline_m=0.5", "truth_initial_state.rho_m[1]=60"]) == want
    assert scn.camera.baseline_m != 0.5  # the input is left as it was


@pytest.mark.parametrize("changes,needle", [
    ({"camera.baseline_m": -1}, "camera.baseline_m: Input should be greater than 0"),
    ({"camera.no_such_key": 1}, "camera.no_such_key: unknown key"),
    ({"filters[7].type": "ekf"}, "index [7] is out of range"),
    ({"camera..x": 1}, "is not a key path"),
    (["camera.baseline_m=1,2"], "one value per key path"),
])  # fmt: skip
def test_edit_errors_are_one_line_each(scn, changes, needle):
    with pytest.raises(api.SpmcError) as e:
        api.edit(scn, changes)
    assert len(e.value.lines) == 1 and needle in e.value.lines[0], e.value.lines


def test_to_yaml_loads_back(scn, tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text(api.to_yaml(scn))
    assert api.load(f) == scn


# ------------------------------------------------------------------------------------------------ runs


def test_run_tables_are_the_parquet_files_with_units(run3):
    t = run3.trials
    assert t.equals(pd.read_parquet(run3.path / "trials.parquet"))
    assert sorted(set(t["trial"])) == [0, 1, 2] and list(dict.fromkeys(t["filter"])) == ["iekf", "ekf"]
    schema = pq.read_schema(run3.path / "timeseries.parquet")
    units = {f.name: f.metadata[b"unit"].decode() for f in schema}
    assert run3.timeseries.attrs["units"] == units and units["e_rho"] == "m" and units["t"] == "s"
    assert len(run3.timeseries) == 3 * 2 * 13  # trials x filters x steps
    assert run3.percentiles.attrs["units"]["percentile"] == "%"
    assert run3.manifest["trials"] == 3 and run3.manifest["kind"] == "run"
    assert run3.chunks["last"].max() == 2
    assert run3.n_trials == 3 and run3.wall_s > 0


def test_open_reads_the_same_run(run3):
    r = api.Run.open(run3.path)
    assert r.trials.equals(run3.trials) and r.scenario == run3.scenario and r.wall_s is None
    assert r.summary() == run3.summary() and "3 of 3 trials (the trials not lost)" in r.summary()


def test_open_refuses_a_directory_that_is_not_a_run(tmp_path):
    with pytest.raises(api.SpmcError, match="not a run directory"):
        api.Run.open(tmp_path)


def test_rerun_reproduces_a_trial(run3, tmp_path):
    rr = run3.rerun(2)
    assert rr.identical
    stored = run3.trials[run3.trials["trial"] == 2].reset_index(drop=True)
    assert rr.trials.equals(stored)
    ts = run3.timeseries
    want = ts[ts["trial"] == 2].reset_index(drop=True)
    pd.testing.assert_frame_equal(rr.timeseries.reset_index(drop=True), want, check_dtype=False)
    kept = run3.rerun(2, tmp_path / "t2.parquet")
    assert (tmp_path / "t2.parquet").is_file() and kept.lines[-1].startswith("time series -> ")


def test_seed_and_trials_options(scn, run3, tmp_path):
    r = api.run(scn, out=tmp_path / "s7", seed=7, trials=2, timeseries="none")
    assert r.manifest["seed"] == 7 and r.n_trials == 2 and not (r.path / "timeseries.parquet").exists()
    assert not r.trials[["e_rho"]].equals(run3.trials[run3.trials["trial"] < 2][["e_rho"]].reset_index(drop=True))
    with pytest.raises(api.SpmcError, match="timeseries 'none'"):
        r.timeseries  # noqa: B018


def test_resume_extends_a_run_to_the_same_bytes(scn, run3, tmp_path):
    out = tmp_path / "grow"
    api.run(scn, out=out, trials=2)
    r = api.resume(out, trials=3)
    assert r.n_trials == 3
    assert (out / "trials.parquet").read_bytes() == (run3.path / "trials.parquet").read_bytes()


@pytest.mark.parametrize("kw,needle", [
    ({"backend": "threads"}, "--backend must be auto, fork, threading, loky or dask"),
    ({"kernels": "gpu"}, "--kernels must be numpy or compiled"),
    ({"backend": "loky", "scheduler": "tcp://x:1"}, "needs --backend dask"),
    ({"timeseries": "some"}, "--timeseries must be one of"),
])  # fmt: skip
def test_bad_run_options_are_one_line_and_write_nothing(scn, tmp_path, kw, needle):
    with pytest.raises(api.SpmcError) as e:
        api.run(scn, out=tmp_path / "r", **kw)
    assert len(e.value.lines) == 1 and needle in e.value.lines[0]


def test_existing_run_directory_needs_overwrite(scn, run3):
    with pytest.raises(api.SpmcError, match="overwrite"):
        api.run(scn, out=run3.path)


def test_report_of_a_run_and_of_a_folder(run3, tmp_path):
    html = run3.report()
    assert html == run3.path / "report.html" and "iekf" in html.read_text()
    res = api.report([run3.path.parent, tmp_path / "nothing"])
    assert run3.path.parent / "index.html" in res.written
    assert len(res.problems) == 1 and "nothing" in res.problems[0]


# ------------------------------------------------------------------------------------------------ studies


def test_sweep_runs_one_campaign_per_point(tmp_path):
    f = write_scenario(tmp_path / "s.yaml", trials=2, time=SHORT)
    s = api.sweep(f, {"camera.baseline_m": [0.5, 1.0]}, out=tmp_path / "sw")
    assert len(s.ran) == 2 and not s.skipped
    assert [r.scenario.camera.baseline_m for r in s.points.values()] == [0.5, 1.0]
    assert len(s.summary()) == 2 * 2 and set(s.percentiles["filter"].str.split("/").str[0]) == set(s.points)
    again = api.sweep(f, ["camera.baseline_m=0.5,1.0"], out=tmp_path / "sw")  # the same sweep: resumed, all done
    assert again.skipped == list(s.points) and not again.ran
    assert s.report() == tmp_path / "sw" / "report.html"
    with pytest.raises(api.SpmcError, match="different sweep"):
        api.sweep(f, {"camera.baseline_m": [2.0]}, out=tmp_path / "sw")


def test_tune_returns_the_tuned_entry_and_scenario(scn, tmp_path):
    out = tmp_path / "tuned.yaml"
    t = api.tune(scn, "iekf", trials=2, max_evaluations=2, out=out)
    assert t.result.evaluations <= 2 and list(t.table.columns) == ["before", "after"]
    assert yaml.safe_load(out.read_text()) == {"filters": [t.entry]}
    tuned = t.scenario.filters[0].process_noise.model_dump()
    assert tuned == pytest.approx(t.entry["process_noise"])
    assert t.scenario.filters[1] == scn.filters[1]  # the other filter is untouched
    with pytest.raises(api.SpmcError, match="at least 2"):
        api.tune(scn, "iekf", trials=1)
    with pytest.raises(api.SpmcError, match="ukf"):
        api.tune(scn, "ukf", trials=2, max_evaluations=1)


def test_public_names():
    assert {"load", "from_dict", "edit", "run", "resume", "Run", "sweep", "tune", "export", "report",
            "SpmcError"} <= set(api.__all__)  # fmt: skip
    assert all(getattr(api, n).__doc__ for n in api.__all__ if n != "Scenario")  # Scenario: config/schema.py
