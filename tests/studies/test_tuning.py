"""``spmc tune`` on real campaigns (issue 35, item 3): the trials ``spmc run`` runs, R and P0, held-back trials."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from scenarios import scenario_dict

from stereopose_mc import api
from stereopose_mc.config import load_scenario, load_scenario_text
from stereopose_mc.config.resolve import filter_setup_of, setup_of
from stereopose_mc.mc import engine
from stereopose_mc.studies import tuning
from stereopose_mc.studies.tuning import TuneError, parse_space, scenario_of

SHORT = {"dt_s": 1.0, "duration_s": 15.0, "error_window_start_s": 5.0}
# dispersed case B (as tests/mc/test_dispersed_runs.py): some orbit draws are invalid (lost at step 0), the
# tumble and range are dispersed, the inertia is unknown to the filters
DISP = {
    "truth_initial_state.rho_m": {"dist": "normal", "std": [1.0, 3.0, 1.0]},
    "truth_initial_state.omega_degps": {"dist": "uniform", "low": -0.3, "high": 0.3},
    "target.inertia_kgm2": {"dist": "uniform", "low": [0.8, 0.9, 1.0], "high": [1.0, 1.1, 1.3], "mode": "replace"},
    "leader.orbit.a_km": {"dist": "normal", "std": 350.0, "applies_to": "both"},
}


def _scenario(**over):
    over = {"time": SHORT, **over}
    return load_scenario_text(yaml.safe_dump(scenario_dict("caseB", **over), sort_keys=False), "<test>")


def test_a_dispersed_tuning_evaluates_the_trials_spmc_run_runs(tmp_path):
    """The start's statistics on tuning and held-back trials are those of ``api.run`` of trials 0..N+M-1."""
    d = scenario_dict("caseB", time=SHORT, filters=[{"type": "ekf"}, {"type": "iekf"}])
    d["dispersions"] = DISP
    scn = load_scenario_text(yaml.safe_dump(d, sort_keys=False), "<test>")
    res = tuning.tune(scn, "iekf", trials=6, check_trials=5, max_evaluations=1)
    assert res.before.trial_ids == tuple(range(6)) and res.check_before.trial_ids == tuple(range(6, 11))
    run = api.run(scn, trials=11, out=tmp_path / "run", timeseries="none")
    df = run.trials[run.trials["filter"] == "iekf"]
    assert df["invalid"].any()  # the seed draws invalid orbits: the dispersed trials, not the shared truth
    for ev, rows in ((res.before, df[df["trial"] < 6]), (res.check_before, df[df["trial"] >= 6])):
        assert ev.trials == len(rows) and ev.lost == int(rows["lost"].sum()) and ev.lost > 0
        assert ev.inconsistent == int(rows["inconsistent"].sum())
        ok = rows[~rows["lost"]]
        assert ev.nees["nees_gauge"] == pytest.approx(ok["nees_gauge_mean"].median() / ok["nees_gauge_dof"].iloc[0])
        assert ev.nis == pytest.approx(ok["nis_ratio_mean"].median())
        assert ev.errors["e_theta"] == pytest.approx(ok["e_theta"].median())


def test_an_evaluation_on_two_cores_is_the_same_as_on_one(monkeypatch):
    """Each evaluation's trials in chunks over the jobs (threads with the compiled kernels): the same search, the same
    statistics, bit for bit, as one chunk in this thread."""
    one = tuning.tune(_scenario(), "iekf", trials=6, check_trials=4, max_evaluations=3, jobs=1)
    monkeypatch.setattr(engine, "AUTO_CHUNK_MIN", 2)  # case B's 6 trials split as a larger state's would be
    seen, real = [], engine._iterate

    def spy(scenario_json, chunks, opts, info=None, *args, **kwargs):
        info = {} if info is None else info
        out = list(real(scenario_json, chunks, opts, info, *args, **kwargs))
        seen.append((len(chunks), info["ran_as"]))
        return out

    monkeypatch.setattr(engine, "_iterate", spy)
    two = tuning.tune(_scenario(), "iekf", trials=6, check_trials=4, max_evaluations=3, jobs=2)
    assert seen == [(2, "threading")] * (len(two.history) + 2)  # every evaluation, the two checks too
    assert len(one.history) == len(two.history) == 3
    for a, b in zip(one.history + [one.check_before, one.check_after], two.history + [two.check_before,
                                                                                        two.check_after]):
        assert (a.params, a.nees, a.nis, a.errors, a.trial_ids, a.lost) == (b.params, b.nees, b.nis, b.errors,
                                                                            b.trial_ids, b.lost)
        assert all(math.isfinite(v) for v in a.nees.values())


def test_held_back_trials_are_disjoint_from_the_tuning_trials():
    res = tuning.tune(_scenario(), "iekf", trials=4, check_trials=3, max_evaluations=2)
    tuned, held = set(res.before.trial_ids), set(res.check_before.trial_ids)
    assert tuned == set(range(4)) and held == set(range(4, 7)) and not tuned & held
    assert set(res.after.trial_ids) == tuned and set(res.check_after.trial_ids) == held
    assert all(set(ev.trial_ids) == tuned for ev in res.history)
    assert tuning.tune(_scenario(), "iekf", trials=4, check_trials=0, max_evaluations=1).check_before is None


def test_scales_map_to_the_filter_entry_and_the_initial_covariance():
    scn = _scenario(filters=[{"type": "ekf"}, {"type": "iekf", "measurement_noise": {"flow_sigma": 4e-5}}])
    params = {"Q.rho": 2e-7, "R.image": 10.0, "R.flow": 0.5, "P0.rho_dot": 100.0}
    out = scenario_of(scn, 1, params)
    old, new = (filter_setup_of(s.filters[1], setup_of(s)) for s in (scn, out))
    assert new.sigma_image == pytest.approx(10.0 * 1e-5)  # the truth's image sigma (caseB: 1e-5), x10
    assert new.sigma_flow == pytest.approx(0.5 * 4e-5)  # the filter's own flow sigma, x0.5
    assert new.Q_diag[0] == pytest.approx(2e-7) and np.array_equal(new.Q_diag[3:], old.Q_diag[3:])
    assert out.filters[0] == scn.filters[0]  # the other filter untouched
    assert out.initial_covariance.rho_dot_m2ps2 == pytest.approx(100.0 * scn.initial_covariance.rho_dot_m2ps2)
    assert out.initial_covariance.rho_m2 == scn.initial_covariance.rho_m2
    shared = scenario_of(scn, 0, {"R": 3.0, "P0": 0.1})
    fs = filter_setup_of(shared.filters[0], setup_of(shared))
    assert (fs.sigma_image, fs.sigma_flow) == pytest.approx((3e-5, 3e-5))
    assert shared.initial_covariance.model_dump() == pytest.approx({k: 0.1 * v for k, v in
                                                                   scn.initial_covariance.model_dump().items()})  # fmt: skip


def test_r_scales_a_pixel_camera_in_pixels():
    scn = load_scenario("configs/mission-realistic.yaml")
    f_px = setup_of(scn).sensor.pixels.f_px
    before = filter_setup_of(scn.filters[0], setup_of(scn))
    out = scenario_of(scn, 0, {"R.image": 2.0})
    mn = out.filters[0].measurement_noise
    assert mn.image_sigma_px == pytest.approx(2.0 * before.sigma_image * f_px, rel=2e-3)  # 3 significant digits
    assert filter_setup_of(out.filters[0], setup_of(out)).sigma_flow == before.sigma_flow


def test_parse_space():
    assert parse_space("q, r,p0") == ("q", "r", "p0")
    assert parse_space(["r_image", "r_flow"]) == ("r_image", "r_flow")
    for bad, why in (("q,x", "unknown 'x'"), ("", "nothing"), ("r,r_image", "exclude"), ("p0,p0_all", "exclude")):
        with pytest.raises(TuneError, match=why):
            parse_space(bad)


def test_tuning_r_finds_a_filter_whose_r_is_ten_times_too_small():
    """The filter assumes image and flow sigmas 1e-6 where the truth's are 1e-5: tuning R alone brings the factor
    to 10 (the truth) and the held-back NIS/dof from ~85 to ~1."""
    scn = _scenario(time={**SHORT, "duration_s": 30.0},
                    filters=[{"type": "iekf", "measurement_noise": {"image_sigma": 1e-6, "flow_sigma": 1e-6}}])  # fmt: skip
    t = api.tune(scn, "iekf", trials=8, check_trials=8, space="r", max_evaluations=12)
    assert t.result.after.params["R"] == pytest.approx(10.0)
    assert t.entry["measurement_noise"] == {"image_sigma": 1e-5, "flow_sigma": 1e-5}
    before, after = t.result.check_before, t.result.check_after
    assert before.nis > 20.0 and abs(math.log(after.nis)) < 0.2
    assert after.inconsistent < before.inconsistent
    assert list(t.check.columns) == ["before", "after"] and t.check.loc["trials", "after"] == 8


def test_tuned_yaml_has_the_initial_covariance_when_p0_was_tuned():
    t = api.tune(_scenario(), "iekf", trials=2, check_trials=0, space="p0_all", max_evaluations=2)
    data = yaml.safe_load(t.yaml)
    assert set(data) == {"filters", "initial_covariance"} and "measurement_noise" not in data["filters"][0]
    assert data["initial_covariance"] == t.scenario.initial_covariance.model_dump()
    assert set(yaml.safe_load(api.tune(_scenario(), "iekf", trials=2, check_trials=0, max_evaluations=1).yaml)) == {
        "filters"}  # fmt: skip
