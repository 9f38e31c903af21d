"""Runs measured by tracks (mc/tracked.py): rendered images and the tracker in the loop, and a replay of tracks.

- an images campaign (a small, low-resolution caseB-images) writes tracks.parquet with the audit, fills the
  feature slots, and counts only the occupied slots in its NEES degrees of freedom;
- replaying that campaign's own tracks.parquet (``source: tracks``) with its truth as a truth file reproduces
  its filter results bit for bit;
- without a truth file the errors are NaN and the run still says what the filter detected; bad files give a
  one-line error and exit code 2.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from stereopose_mc.config import load_scenario
from stereopose_mc.mc import engine
from stereopose_mc.sim import tracks_file

from ..cli_helpers import one_error_line, spmc

ROOT = Path(__file__).resolve().parents[2]
TRIALS = 10  # the small CI campaign (at 384 px: at 256 px and 40 deg the box is ~17 px wide, no features)


def _images_scenario(tmp: Path) -> Path:
    d = yaml.safe_load((ROOT / "configs" / "caseB-images.yaml").read_text())
    d["time"]["duration_s"] = 12.0
    d["camera"]["resolution_px"] = [384, 384]
    d["camera"]["fov_deg"] = 24.0  # the same focal length in pixels, the target still in view
    d["measurements"]["images"]["cache"] = False
    p = tmp / "images.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


@pytest.fixture(scope="module")
def images_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("tracked")
    cfg = _images_scenario(tmp)
    scn = load_scenario(cfg)
    engine.run(scn, tmp / "run", engine.RunOptions(trials=TRIALS, jobs=1, overwrite=True, command=["test"]))
    return tmp, cfg, scn


def test_images_campaign_writes_its_tracks_and_fills_the_slots(images_run):
    tmp, _, scn = images_run
    tracks = pd.read_parquet(tmp / "run" / "tracks.parquet")
    trials = pd.read_parquet(tmp / "run" / "trials.parquet")
    assert sorted(tracks["trial"].unique()) == list(range(TRIALS))
    assert {"track_id", "col_r", "disparity_px", "body_x", "clean"} <= set(tracks.columns)
    assert len(trials) == TRIALS and np.isfinite(trials["e_theta"]).any()
    n = 13 + 3 * scn.target.feature_slots + 2
    # slots left free (fewer live tracks than slots at some step) leave the NEES: its mean dof is below n - 4
    live = tracks.groupby(["trial", "step"]).size()
    dof = trials["dof_nees_gauge"].to_numpy()
    assert (dof <= n - 4).all() and (dof > 0).all()
    if live.min() < scn.target.feature_slots:
        assert (dof < n - 4).any()


def _replay(tmp: Path, cfg: Path, truth_file: bool) -> Path:
    d = yaml.safe_load(cfg.read_text())
    d["measurements"].pop("images")
    d["measurements"]["source"] = "tracks"
    d["measurements"]["tracks"] = {"file": str(tmp / "run" / "tracks.parquet")}
    if truth_file:
        scn = load_scenario(cfg)
        x = engine.prepare(scn).truth.x
        t = pd.DataFrame(x[:, :13], columns=list(tracks_file.STATE_COLUMNS))
        t.insert(0, "step", np.arange(len(t), dtype=np.int64))
        tracks_file.write_tracks(t, tmp / "truth.parquet")  # any table: Parquet, atomically
        d["measurements"]["tracks"]["truth_file"] = "truth.parquet"
    else:  # no true angular acceleration: a differentiated source for the pseudo-measurement
        d["measurements"]["inertia_pseudo_measurement"].update(angular_acceleration="savitzky_golay", window=9, polyorder=2)
    p = tmp / f"replay-{truth_file}.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


def test_a_replay_of_the_campaign_tracks_reproduces_its_results_bit_for_bit(images_run):
    tmp, cfg, _ = images_run
    scn = load_scenario(_replay(tmp, cfg, truth_file=True))
    engine.run(scn, tmp / "replay", engine.RunOptions(trials=TRIALS, jobs=1, overwrite=True, command=["test"]))
    a = pd.read_parquet(tmp / "run" / "trials.parquet")
    b = pd.read_parquet(tmp / "replay" / "trials.parquet")
    cols = [c for c in a.columns if c.startswith(("e_", "final_", "nees", "nis", "lost", "dof_"))]
    pd.testing.assert_frame_equal(a[cols], b[cols])
    ta = pd.read_parquet(tmp / "run" / "timeseries.parquet")
    tb = pd.read_parquet(tmp / "replay" / "timeseries.parquet")
    pd.testing.assert_frame_equal(ta, tb)


def test_tracks_without_truth_give_no_errors_but_run(images_run):
    tmp, cfg, _ = images_run
    scn = load_scenario(_replay(tmp, cfg, truth_file=False))
    engine.run(scn, tmp / "blind", engine.RunOptions(trials=TRIALS, jobs=1, overwrite=True, command=["test"]))
    b = pd.read_parquet(tmp / "blind" / "trials.parquet")
    assert len(b) == TRIALS and b["e_theta"].isna().all() and b["nees_gauge_mean"].isna().all()
    assert np.isfinite(b["nis_mean"]).all()


def test_a_bad_tracks_file_is_one_line_and_exit_2(images_run, tmp_path):
    tmp, cfg, _ = images_run
    bad = tmp_path / "bad.csv"
    pd.read_parquet(tmp / "run" / "tracks.parquet").drop(columns="col_l").to_csv(bad, index=False)
    d = yaml.safe_load(_replay(tmp, cfg, truth_file=True).read_text())
    d["measurements"]["tracks"] = {"file": str(bad), "truth_file": str(tmp / "truth.parquet")}
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(d))
    one_error_line(spmc("run", p, "--trials", 2, "--out", tmp_path / "out", "--quiet"), "bad.csv", "col_l")
    assert not (tmp_path / "out" / "trials.parquet").exists()


def test_the_report_shows_the_tracker_audit(images_run):
    """`spmc report` of an images run: the tracker section's counts are those of its tracks.parquet."""
    from stereopose_mc.outputs.report import build_run_report

    tmp, _, _ = images_run
    html = build_run_report(tmp / "run").read_text()
    tracks = pd.read_parquet(tmp / "run" / "tracks.parquet")
    n = tracks.groupby(["trial", "track_id"]).ngroups
    assert "Tracker and its truth audit" in html
    assert f"<td class=\"l\">tracks</td><td>{n}</td>" in html.replace("\n", "")


def test_dispersed_images_render_each_trial_its_own(tmp_path):
    """Dispersions with source images: every trial rendered along its own truth (here a dispersed range and tumble
    axis), so the tracks differ between trials; a trial rerun alone gets the same tracks and filter results."""
    d = yaml.safe_load(_images_scenario(tmp_path).read_text())
    d["time"].update(duration_s=6.0, error_window_start_s=2.0)
    d["dispersions"] = {"sampling": "random",
                        "truth_initial_state.rho_m": {"dist": "normal", "std": [0.5, 3.0, 0.5]},
                        "truth_initial_state.omega_degps": {"dist": "uniform_direction",
                                                            "magnitude": {"dist": "uniform", "low": 0.5, "high": 1.0},
                                                            "applies_to": "both"}}  # fmt: skip
    p = tmp_path / "dispersed.yaml"
    p.write_text(yaml.safe_dump(d))
    scn = load_scenario(p)
    engine.run(scn, tmp_path / "run", engine.RunOptions(trials=2, jobs=1, overwrite=True, command=["test"]))
    tracks = pd.read_parquet(tmp_path / "run" / "tracks.parquet")
    t = pd.read_parquet(tmp_path / "run" / "trials.parquet")
    assert sorted(tracks["trial"].unique()) == [0, 1] and len(t) == 2 and not t["invalid"].any()
    a, b = (tracks[tracks["trial"] == j] for j in (0, 1))
    first = lambda x: x[x["step"] == 0]["col_r"].to_numpy()  # noqa: E731
    assert len(first(a)) and len(first(b)) and not np.array_equal(np.sort(first(a)), np.sort(first(b)))
    co = engine.compute_chunk(scn.model_dump_json(), np.array([1]), "none")
    one = co.trials_table.to_pandas()
    cols = ["e_rho", "e_theta", "nees_gauge_mean", "dof_nees_gauge"]
    pd.testing.assert_frame_equal(one[cols].reset_index(drop=True), t[t["trial"] == 1][cols].reset_index(drop=True))
