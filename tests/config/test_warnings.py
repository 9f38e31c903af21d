"""``spmc validate`` warnings (issue 33, item 8): exit 0, one ``file:line: key: warning: ...`` line each."""

from __future__ import annotations

import yaml
from cli_helpers import spmc
from scenarios import scenario_dict


def _write(path, d):
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


def test_dispersion_on_the_truth_beyond_p0_warns(tmp_path):
    d = scenario_dict("caseB", trials=4)
    d["dispersions"] = {
        "truth_initial_state.rho_m": {"dist": "normal", "std": [1.0, 5.0, 1.0]},  # 5 m against P0 sigma 1 m
        "truth_initial_state.rho_dot_mps": {"dist": "uniform", "low": -0.1, "high": 0.1},  # 0.058 < 1 m/s: quiet
        "truth_initial_state.omega_degps": {"dist": "normal", "std": 3.0, "applies_to": "both"},  # both: quiet
    }
    f = _write(tmp_path / "s.yaml", d)
    r = spmc("validate", f)
    assert r.exit_code == 0, r.output
    lines = [ln for ln in r.output.splitlines() if "warning:" in ln]
    line = next(i + 1 for i, t in enumerate(f.read_text().splitlines()) if t.strip().startswith("truth_initial_state.rho_m"))
    assert len(lines) == 1 and lines[0].startswith(f"{f}:{line}: dispersions.truth_initial_state.rho_m: warning:")
    assert "sigma 5 m" in lines[0] and "initial sigma 1 m" in lines[0] and "applies_to: both" in lines[0]


def test_features_never_in_view_warn(tmp_path):
    d = scenario_dict("caseB", trials=4)
    d["camera"] = {"baseline_m": 1.0, "resolution_px": [1024, 1024], "fov_deg": 0.01}  # the target is out of view
    d["measurements"] = {k: v for k, v in d["measurements"].items() if k not in ("image_sigma", "flow_sigma")}
    d["measurements"].update(image_sigma_px=0.2, flow_sigma_pxps=0.1)
    f = _write(tmp_path / "s.yaml", d)
    r = spmc("validate", f)
    assert r.exit_code == 0, r.output
    assert f"{f}:" in r.output and "camera: warning: no feature point is ever in view" in r.output
    d["camera"]["fov_deg"] = 40.0
    assert "warning" not in spmc("validate", _write(tmp_path / "ok.yaml", d)).output


def test_a_blind_scenario_loses_its_trials_with_their_own_reason(tmp_path):
    """Issue 33 item 6: no feature measured is a distinct lost reason, not 'inconsistent'."""
    import numpy as np

    from stereopose_mc.config import load_scenario
    from stereopose_mc.mc import engine
    from stereopose_mc.mc.trial import run_chunk

    d = scenario_dict("caseB", trials=2, time={"dt_s": 1.0, "duration_s": 15.0, "error_window_start_s": 2.0},
                      divergence={"nis_start_s": 2.0, "nis_window_steps": 3})  # fmt: skip
    d["camera"] = {"baseline_m": 1.0, "resolution_px": [1024, 1024], "fov_deg": 0.01}
    d["measurements"] = {k: v for k, v in d["measurements"].items() if k not in ("image_sigma", "flow_sigma")}
    d["measurements"].update(image_sigma_px=0.2, flow_sigma_pxps=0.1)
    scn = load_scenario(_write(tmp_path / "s.yaml", d))
    pr = engine.prepare(scn)
    r = run_chunk(scn.seed, np.arange(2), pr.setup, pr.truth, pr.exact, pr.filters, pr.bounds).runs[0]
    assert (r.lost_step == 4).all()  # the first window t = 2, 3, 4 s
    assert all(x == "filter lost: no feature measured at any of 3 steps" for x in r.lost_reason)
