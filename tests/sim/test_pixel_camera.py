"""The pixel camera: conversion to normalized units, features outside the images."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from stereopose_mc.config import load_scenario_text
from stereopose_mc.config.resolve import filter_setup_of, setup_of
from stereopose_mc.core import camera
from stereopose_mc.sim import measurements as meas
from stereopose_mc.sim.truth import simulate_truth

from scenarios import scenario_dict

SHORT = {"dt_s": 1.0, "duration_s": 10.0, "error_window_start_s": 2.0}


def load(cam, meas_over=None, filters=None):
    d = scenario_dict(time=SHORT)
    d["camera"].update(cam)
    d["measurements"].update(meas_over or {})
    if filters is not None:
        d["filters"] = filters
    return load_scenario_text(yaml.safe_dump(d))


def test_pixel_noise_is_converted_with_the_focal_length():
    scn = load({"resolution_px": [1024, 768], "fov_deg": 40.0}, {"image_sigma_px": 0.2, "flow_sigma_pxps": 0.05},
               [{"type": "iekf", "measurement_noise": {"image_sigma_px": 0.5}}])
    s = setup_of(scn)
    f = 512.0 / math.tan(math.radians(20.0))  # 1406.7 px
    assert s.sensor.pixels.f_px == pytest.approx(f, rel=1e-12)
    assert s.sigma_image == pytest.approx(0.2 / f, rel=1e-12)
    assert s.sigma_flow == pytest.approx(0.05 / f, rel=1e-12)
    fs = filter_setup_of(scn.filters[0], s)
    assert fs.sigma_image == pytest.approx(0.5 / f, rel=1e-12)
    assert fs.sigma_flow == pytest.approx(0.05 / f, rel=1e-12)  # default: the truth's
    # image extent in normalized coordinates: [-W/2, W/2] / f and [-H/2, H/2] / f
    np.testing.assert_allclose(s.sensor.pixels.bounds(), [-512 / f, 512 / f, -384 / f, 384 / f])


def test_focal_length_px_and_principal_point():
    s = setup_of(load({"resolution_px": [640, 480], "focal_length_px": 800.0, "principal_point_px": [300.0, 250.0]}))
    np.testing.assert_allclose(s.sensor.pixels.bounds(), [-300 / 800, 340 / 800, -250 / 800, 230 / 800])


def test_features_outside_a_narrow_field_of_view_are_not_measured():
    # case B: target at [10, 60, 10] m, features 1.5 m from its centre, so v = 0.167 +- 0.025;
    # a 24 deg FOV on a 1000 x 800 image reaches v = tan(12 deg) 400 / 500 = 0.170: some points leave it
    scn = load({"resolution_px": [1000, 800], "fov_deg": 24.0})
    s = setup_of(scn)
    truth = simulate_truth(s)
    vis = meas.noise_free(s, truth).visible
    rho_i, _ = camera.feature_kinematics(truth.x)
    h = math.tan(math.radians(12.0))
    u_r, u_l, v = rho_i[..., 0] / rho_i[..., 1], (rho_i[..., 0] - 1.0) / rho_i[..., 1], rho_i[..., 2] / rho_i[..., 1]
    expected = (np.abs(u_r) <= h) & (np.abs(u_l) <= h) & (np.abs(v) <= 0.8 * h) & (rho_i[..., 1] > 0)
    np.testing.assert_array_equal(vis, expected)
    assert 0 < vis.sum() < vis.size
    # the default (no resolution) sees everything in front
    assert meas.noise_free(setup_of(load({})), truth).visible.all()


@pytest.mark.parametrize("bad, msg", [
    ({"camera": {"resolution_px": [100, 100]}}, "exactly one of fov_deg or focal_length_px"),
    ({"camera": {"fov_deg": 40.0}}, "need resolution_px"),
    ({"measurements": {"image_sigma_px": 0.3}}, "needs camera.resolution_px"),
])  # fmt: skip
def test_pixel_options_validate(bad, msg):
    d = scenario_dict(time=SHORT)
    for k, v in bad.items():
        d[k].update(v)
    with pytest.raises(Exception, match=msg):
        load_scenario_text(yaml.safe_dump(d))
