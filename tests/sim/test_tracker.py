"""The stereo KLT tracker on rendered sequences, judged by the renderer's truth (the audit)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stereopose_mc.config.loader import load_scenario
from stereopose_mc.config.resolve import setup_of
from stereopose_mc.config.sensor import PixelCamera
from stereopose_mc.core import quaternion as qt, shapes
from stereopose_mc.sim.render import renderer as rr, scene as sc, sensor as ss
from stereopose_mc.sim.render.setup import ImageSetup, image_setup
from stereopose_mc.sim.tracker import audit, klt
from stereopose_mc.sim.truth import simulate_truth

ROOT = __import__("pathlib").Path(__file__).resolve().parents[2]
SETTINGS = klt.TrackerSettings(window_px=15, min_distance_px=6.0, max_tracks=80, min_tracks=40)


def _sequence(setup: ImageSetup, poses, seed: int):
    rng = np.random.default_rng(seed)
    sensor = ss.SensorModel()
    for rho, D in poses:
        f = rr.render_stereo(setup.scene, setup.rig, rho, D, setup.sun_L)
        yield ss.expose(f.right.radiance, sensor, rng), ss.expose(f.left.radiance, sensor, rng)


def _rz(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def turning():
    """A textured box at 10 m, 256 px, turning 1 deg per frame about the image's vertical for 50
    frames: its +x face starts 40 deg open to the cameras and turns away near frame 40."""
    cam = PixelCamera(256, 256, 128 / np.tan(np.radians(20)), 128.0, 128.0)
    sun = np.array([0.7, -1.0, -0.3]) / np.linalg.norm([0.7, -1.0, -0.3])  # lights the +x face and the front
    setup = ImageSetup(sc.scene(shapes.box([2.0, 1.5, 3.0]), 7), rr.Rig(cam, 1.0), sun)
    tilt = qt.dcm(qt.from_axis_angle(np.array([1.0, 0.0, 0.0]), np.radians(-20.0)))
    poses = [(np.array([0.3, 10.0, -0.2]), tilt @ _rz(-40.0 + 1.0 * k)) for k in range(50)]
    tracks = klt.track_sequence(_sequence(setup, poses, 1), 1.0, SETTINGS)
    return setup, poses, tracks, audit.audit(tracks, setup, poses)


def test_clean_features_track_to_a_few_tenths_of_a_pixel(turning):
    _, _, _, a = turning
    s = audit.summary(a)
    assert s["clean_rows"] > 0.8 * s["rows"] > 1000
    assert s["clean_median_err_r_px"] <= 0.3 and s["clean_median_err_l_px"] <= 0.3
    clean = a[a["clean"]]
    assert clean.loc[clean["age"] == 0, "err_r_px"].max() < 1e-6  # the body point is cast through the detection
    # stereo: the left position is the body point's left projection (disparity error included)
    assert clean.loc[clean["age"] == 0, "err_l_px"].median() < 0.15


def test_image_velocities_are_the_tracked_displacements(turning):
    _, poses, t, a = turning
    row = t[t["age"] > 0].iloc[len(t) // 3]
    prev = t[(t["track_id"] == row["track_id"]) & (t["step"] == row["step"] - 1)].iloc[0]
    assert row["dcol_r"] == pytest.approx(row["col_r"] - prev["col_r"])
    assert row["drow_l"] == pytest.approx(row["row_l"] - prev["row_l"])
    assert t.loc[t["age"] == 0, "dcol_r"].isna().all() and t.loc[t["age"] > 0, "dcol_r"].notna().all()
    assert (t["disparity_px"] < 0).all()  # the point model's sign: d = col_l - col_r = -f b / y
    assert t["quality"].between(0.0, 1.0).all() and t["quality"].median() > 0.8


def test_ids_persist_and_count_up(turning):
    _, _, t, _ = turning
    for _, g in t.groupby("track_id"):
        steps = g["step"].to_numpy()
        assert np.array_equal(steps, np.arange(steps[0], steps[0] + len(steps)))  # no gaps
        assert np.array_equal(g["age"].to_numpy(), np.arange(len(steps)))
        assert len(steps) < 2 or np.abs(np.diff(g["col_r"].to_numpy())).max() < 3.0  # one point, not a re-used id
    born = t.groupby("track_id")["step"].min()
    assert born.is_monotonic_increasing  # ids count up with time and are never reused
    life = t.groupby("track_id").size()
    assert life.median() >= 10 and (life >= 30).sum() >= 10


def test_tracks_on_a_face_turning_away_end_and_new_ones_are_detected(turning):
    setup, poses, t, a = turning
    P = a[["body_x", "body_y", "body_z"]].to_numpy()
    on_x = np.isclose(P[:, 0], 1.0)  # on the +x face (half-size 1 m)
    last = a.groupby("track_id")["step"].max()
    ids_x = a.loc[on_x, "track_id"].unique()
    assert len(ids_x) >= 5
    # the +x face's outward normal turns away from the right camera at the step where n . (c - p) < 0
    centre = np.array([1.0, 0.0, 0.0])
    gone = next(k for k, (rho, D) in enumerate(poses) if (D @ [1.0, 0, 0]) @ (-(D @ centre + rho)) < 0)
    assert 30 < gone < 50
    assert (last.loc[ids_x] < gone).all()
    born = a.groupby("track_id")["step"].min()
    ended = last.loc[ids_x]
    # the face's tracks end while it narrows; re-detection refills the count with tracks elsewhere
    assert (born > ended.median()).sum() >= 10
    assert not np.isclose(a.loc[a["track_id"].isin(born[born > ended.max()].index), "body_x"], 1.0).any()
    assert t.groupby("step").size().iloc[ended.max() + 1 :].min() >= SETTINGS.min_tracks


def test_audit_flags_a_track_that_slides_off_its_surface(turning):
    setup, poses, t, _ = turning
    bad = t.copy()
    tid = bad.groupby("track_id")["step"].size().idxmax()  # the longest track
    sel = (bad["track_id"] == tid) & (bad["age"] >= 5)
    bad.loc[sel, "col_r"] += 0.7 * (bad.loc[sel, "age"] - 4)  # drifting away 0.7 px per step
    a = audit.audit(bad, setup, poses)
    mine = a[a["track_id"] == tid]
    assert mine["err_r_px"].iloc[-1] == pytest.approx(0.7 * (len(mine) - 5), abs=0.5)
    assert mine["jumped"].all() and not mine["clean"].any()
    others = audit.audit(t, setup, poses)
    assert others.loc[others["track_id"] == tid, "clean"].all()


def test_edge_tests_reject_dark_edges_straight_edges_and_depth_steps():
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.uniform(40, 220, (120, 240)).astype(np.float32), (0, 0), 1.5)
    img = np.clip(tex, 0, 255).astype(np.uint8)
    p = np.array([[60.0, 60.0]])
    s = klt.TrackerSettings()
    assert klt.edge_free(img, p, s).all()
    shadow = img.copy()
    shadow[:, :60] = 2  # a shadow edge through the window
    assert not klt.edge_free(shadow, p, s).any()
    step = np.where(np.arange(240) < 60, 60, 180).astype(np.uint8)[None, :].repeat(120, 0)
    assert not klt.edge_free(step, p, s).any()  # a straight untextured edge: aperture problem
    # stereo: a uniform shift of 12 px passes, a window straddling shifts of 12 and 16 px fails
    left = np.roll(img, -12, axis=1)
    pr = np.array([[120.0, 60.0]])
    p_l, _, ok, _ = klt.stereo(img, left, pr, np.array([-10.0]), s)
    assert ok.all() and p_l[0, 0] == pytest.approx(108.0, abs=0.05)
    split = left.copy()  # right columns < 134 at disparity -12, the rest at -16 (a depth step)
    split[:, 122:] = np.roll(img, -16, axis=1)[:, 122:]
    assert klt.stereo(img, split, pr - [20, 0], np.array([-10.0]), s)[2].all()  # away from the step
    assert not klt.stereo(img, split, pr + [14, 0], np.array([-14.0]), s)[2].any()


def test_bundled_example_tracks_100_frames_within_three_tenths_of_a_pixel():
    """configs/mission-realistic.yaml (box 2 x 1.5 x 3 m at 62 m, 1024 px, 40 deg): 100 steps of its truth."""
    s = load_scenario(ROOT / "configs" / "mission-realistic.yaml")
    truth = simulate_truth(setup_of(s))
    setup = image_setup(s)
    poses = [rr.pose_of(x) for x in truth.x]
    t = klt.track_sequence(_sequence(setup, poses, 2), float(truth.t[1] - truth.t[0]), SETTINGS)
    a = audit.audit(t, setup, poses)
    summ = audit.summary(a)
    assert t["step"].nunique() == 101 and summ["tracks"] >= 30
    assert summ["clean_median_err_r_px"] <= 0.3 and summ["clean_median_err_l_px"] <= 0.3
