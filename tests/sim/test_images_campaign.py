"""The image source of a campaign (sim/images.py): render once and cache, per-trial noise, rerun alone."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from scipy.stats import norm

from stereopose_mc.config import load_scenario_text
from stereopose_mc.config.resolve import setup_of
from stereopose_mc.sim import images
from stereopose_mc.sim.render import renderer as rr
from stereopose_mc.sim.render import sensor as ss
from stereopose_mc.sim.tracker import audit, klt
from stereopose_mc.sim.truth import simulate_truth

ROOT = Path(__file__).resolve().parents[2]


def small_scenario(fov_deg: float | None = None, sun=None, **images_keys):
    """configs/caseB-images.yaml at 256 px, 15 m, 10 steps, a faster spin (a few tracks come and go)."""
    d = yaml.safe_load((ROOT / "configs" / "caseB-images.yaml").read_text())
    d["camera"]["resolution_px"] = [256, 256]
    if fov_deg is not None:
        d["camera"]["fov_deg"] = fov_deg
    if sun is not None:
        d["measurements"]["illumination"] = {"sun_direction_lvlh": sun}
    d["time"] = {"dt_s": 1.0, "duration_s": 10.0, "error_window_start_s": 1.0}
    d["truth_initial_state"]["rho_m"] = [2.5, 15.0, 2.5]
    d["truth_initial_state"]["omega_degps"] = [-1.0, -1.0, 0.34]
    d["measurements"]["images"]["tracker"] = {"max_tracks": 40, "min_tracks": 20, "min_distance_px": 6.0,
                                              "window_px": 15}  # fmt: skip
    d["measurements"]["images"].update(images_keys)
    return load_scenario_text(yaml.safe_dump(d))


@pytest.fixture(scope="module")
def small():
    s = small_scenario()
    setup = setup_of(s)
    return s, setup, simulate_truth(setup)


def test_cache_hit_gives_the_rendered_radiance(small, tmp_path):
    s, setup, truth = small
    cfg = images.image_config(s)
    img = images.image_setup(s, cfg.panels)
    poses = [rr.pose_of(x) for x in truth.x]
    r1, hit1 = images.cached_radiance(s, img, poses, cfg.render, tmp_path)
    r2, hit2 = images.cached_radiance(s, img, poses, cfg.render, tmp_path)
    assert (hit1, hit2) == (False, True) and len(list(tmp_path.glob("*.npz"))) == 1
    for a, b in ((r1.right, r2.right), (r1.left, r2.left), (r1.window, r2.window)):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    # the kept window holds the whole rendering: the full image is 0 outside it
    f = rr.render_stereo(img.scene, img.rig, *poses[5], img.sun_L, cfg.render)
    r0, r1_, c0, c1 = r1.window[0]
    assert np.array_equal(r1.right[5], f.right.radiance[r0:r1_, c0:c1].astype(np.float32))
    outside = f.right.radiance.copy()
    outside[r0:r1_, c0:c1] = 0.0
    assert r1.right[5].max() > 0.1 and not outside.any()
    # another Sun is another key
    other = img.__class__(img.scene, img.rig, -img.sun_L)
    assert images.render_key(s, other, poses, cfg.render) != images.render_key(s, img, poses, cfg.render)
    _, hit3 = images.cached_radiance(s, other, poses[:3], cfg.render, tmp_path)
    assert not hit3


def test_earth_background_is_rendered_kept_and_keyed(small):
    """A 70 deg camera 433 km above the Earth at perigee: the limb is 20.6 deg off the optical axis, in view."""
    from stereopose_mc.core.orbit import leader_kinematics

    _, setup, truth = small
    s = small_scenario(fov_deg=70.0, sun=[0.6, -0.6, 0.5], background="earth")
    cfg = images.image_config(s)
    img = images.image_setup(s, cfg.panels)
    assert img.earth is not None and images.image_setup(small[0], cfg.panels).earth is None
    poses = [rr.pose_of(x) for x in truth.x]
    ev = images.earth_views(img, setup.orbit, truth.nu)
    r_leader = leader_kinematics(setup.orbit, truth.t).r
    assert np.allclose([e.centre_L for e in ev], np.c_[-r_leader, np.zeros((len(ev), 2))], rtol=1e-12, atol=0)
    black = img.__class__(img.scene, img.rig, img.sun_L)
    r_e = images.render_radiance(img, poses, cfg.render, earth=ev)
    r_b = images.render_radiance(black, poses, cfg.render)
    (r0, r1, c0, c1), (b0, b1, d0, d1) = r_e.window[0], r_b.window[0]
    assert r0 <= b0 and r1 >= b1 and c0 == 0 and c1 >= d1  # the Earth is on the -x (left) side
    f = rr.render_stereo(img.scene, img.rig, *poses[5], img.sun_L, cfg.render, ev[5])
    assert np.array_equal(r_e.right[5], f.right.radiance[r0:r1, c0:c1].astype(np.float32))
    outside = f.right.radiance.copy()
    outside[r0:r1, c0:c1] = 0.0
    assert not outside.any()
    off_target = r_e.right[5][:, : d0 - c0]  # columns left of the target's window: the Earth alone
    assert (off_target > 0.01).mean() > 0.3 and off_target.max() < 0.61
    keys = {images.render_key(s, img, poses, cfg.render, e) for e in (None, ev, ev[::-1])}
    assert len(keys) == 3
    tracks = images.campaign_tracks(s, setup, truth, [0], s.seed, cache_dir=None)
    assert len(tracks) > 0 and tracks.loc[tracks["clean"], "err_r_px"].median() < 0.3


def test_a_trial_gets_the_same_tracks_alone_or_with_others(small, tmp_path):
    s, setup, truth = small
    both = images.campaign_tracks(s, setup, truth, [0, 3, 1], s.seed, cache_dir=tmp_path)
    alone = images.campaign_tracks(s, setup, truth, [3], s.seed, cache_dir=tmp_path)  # from the cache
    assert list(both.columns) == list(images.TRACK_TABLE_COLUMNS)
    assert both["trial"].unique().tolist() == [0, 3, 1]
    pd.testing.assert_frame_equal(both[both["trial"] == 3].reset_index(drop=True), alone)
    per_trial = both.groupby("trial")["track_id"].nunique()
    assert (per_trial >= 15).all()  # tracks exist; the trials' noise differs, so do their tracks
    a, b = (both[both["trial"] == j][["col_r", "row_r"]].to_numpy() for j in (0, 1))
    assert a.shape != b.shape or not np.array_equal(a, b)
    assert both.loc[both["clean"], "err_r_px"].median() < 0.3  # docs/images.md: the clean tracks' accuracy


def test_campaign_equals_the_documented_chain(small):
    # render -> expose (images_rng: right then left per step) -> klt -> audit, by hand at full frame
    s, setup, truth = small
    cfg = images.image_config(s)
    img = images.image_setup(s, cfg.panels)
    poses = [rr.pose_of(x) for x in truth.x]
    r = images.render_radiance(img, poses, cfg.render)
    rng = images.images_rng(s.seed, 2)
    frames = list(images.trial_frames(r, cfg.sensor, rng))
    got = images.campaign_tracks(s, setup, truth, [2], s.seed, cache_dir=None)
    want = audit.audit(klt.track_sequence(frames, setup.dt, cfg.tracker), img, poses)
    pd.testing.assert_frame_equal(got.drop(columns="trial"), want)


def test_per_trial_truths_render_per_trial(small):
    s, setup, truth = small
    batched = truth.__class__(**{**truth.__dict__, "x": np.stack([truth.x, truth.x])})
    got = images.campaign_tracks(s, setup, batched, [4, 5], s.seed)
    want = images.campaign_tracks(s, setup, truth, [4, 5], s.seed, cache_dir=None)
    pd.testing.assert_frame_equal(got, want)
    empty = images.campaign_tracks(s, setup, truth, [], s.seed)
    assert len(empty) == 0 and list(empty.columns) == list(images.TRACK_TABLE_COLUMNS)
    with pytest.raises(ValueError, match="per-trial truth has 2 trials, not 1"):
        images.campaign_tracks(s, setup, batched, [4], s.seed)


def test_background_noise_probabilities_match_the_sensor_model():
    sensor = ss.SensorModel(read_noise_e=40.0)  # a noisy sensor: ~10 % of dark pixels at 1 DN
    p = images.background_probabilities(sensor)
    half = 0.5 / sensor.gain / sensor.read_noise_e
    assert p[0] == pytest.approx(norm.cdf(half), rel=1e-12)
    assert p[1] == pytest.approx(norm.cdf(3 * half) - norm.cdf(half), rel=1e-12)
    assert p.sum() == pytest.approx(1.0, abs=1e-15)
    # the sensor itself on a dark frame (independent draws): the same frequencies
    dark = ss.expose(np.zeros((400, 500)), sensor, np.random.default_rng(3))
    freq = np.bincount(dark.ravel(), minlength=len(p))[: len(p)] / dark.size
    assert np.allclose(freq, p, atol=5 * np.sqrt(p * (1 - p) / dark.size) + 1e-6)


def test_sparse_background_frames_have_the_dark_frequencies():
    sensor = ss.SensorModel(read_noise_e=12.0)  # P(1 DN) ~ 5e-4: sparse
    p = images.background_probabilities(sensor)
    assert 1 - p[0] < images.SPARSE_BACKGROUND
    rng = np.random.default_rng(5)
    img = np.concatenate([images.expose_window(np.ones((4, 4)), (0, 4, 0, 4), (512, 512), sensor, rng)
                          for _ in range(20)])  # fmt: skip
    assert img.dtype == np.uint8 and img[:4, :4].min() > 150  # the window: the sensor's exposure of white
    dark = img.reshape(20, 512, 512)[:, 4:, :]
    ones = (dark == 1).mean()
    sd = np.sqrt(p[1] / dark.size)
    assert abs(ones - p[1]) < 5 * sd and (dark > 1).mean() < 1e-6


def test_campaign_tables_are_track_files_and_fill_slots_near_the_truth(small, tmp_path):
    from stereopose_mc.config.sensor import pixel_camera_of
    from stereopose_mc.core import camera
    from stereopose_mc.sim.slots import assign_slots, slot_measurements
    from stereopose_mc.sim.tracks_file import read_tracks, write_tracks

    s, setup, truth = small
    tr = images.campaign_tracks(s, setup, truth, [6], s.seed, cache_dir=tmp_path)
    back = read_tracks(write_tracks(tr, tmp_path / "tracks.parquet"))
    pd.testing.assert_frame_equal(back, tr)
    a = assign_slots(tr, 8, setup.steps)
    m = slot_measurements(tr, a, pixel_camera_of(s))
    assert m.measured[1:].sum() >= 8 * setup.steps * 0.8  # the slots stay filled
    # independent reference: the point model's exact measurement of each slot's true body point
    k, i = np.nonzero(m.measured)
    x = truth.x[k]
    x1 = np.concatenate([x[:, :13], m.body[k, i], x[:, -2:]], axis=1)
    exact = camera.h_features(x1, setup.baseline)[:, 0]
    f_px = pixel_camera_of(s).f_px
    err_px = np.abs(m.y[k, i] - exact) * f_px
    assert np.median(err_px[:, :4]) < 0.1 and np.median(err_px[:, 4:]) < 0.2
