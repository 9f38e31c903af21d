"""The perturbed truth (J2, drag, gravity-gradient torque) against an independent inertial propagation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from reference import inertial_perturbed as ref
from reference.truth_setups import ECCENTRIC, elements_of, setup_from

from stereopose_mc.core import perturbed, state as st
from stereopose_mc.core import quaternion as qt
from stereopose_mc.core.orbit import Orbit, elements_to_rv, leader_kinematics
from stereopose_mc.sim.truth import filter_orbit_at, perturbed_relative, simulate_truth

LEO = dict(ECCENTRIC, leader={"orbit": {"a_km": 6878.0, "e": 0.01, "i_deg": 51.6, "raan_deg": 30.0,
                                        "argp_deg": 60.0, "true_anomaly_deg": 45.0}})  # fmt: skip
MODELS = {
    "j2+gg": ({"j2": True, "gravity_gradient_torque": True}, dict(j2=True, gg=True)),
    "j2+gg+drag": ({"j2": True, "gravity_gradient_torque": True,
                    "drag": {"ballistic_coefficient_leader_kgpm2": 20.0, "ballistic_coefficient_target_kgpm2": 80.0}},
                   dict(j2=True, gg=True, drag_b=(20.0, 80.0))),
}  # fmt: skip


def angle_between(q1, q2):
    return 2.0 * np.arccos(np.clip(np.abs(np.sum(q1 * q2, axis=-1)), 0.0, 1.0))


@pytest.mark.parametrize("model", list(MODELS))
def test_perturbed_truth_matches_the_independent_propagation(model):
    cfg, kw = MODELS[model]
    setup = setup_from(**LEO, truth_model=cfg)
    assert setup.times[-1] >= 1000.0
    truth = simulate_truth(setup)
    x0 = setup.x0
    moments = np.array([np.exp(x0[-2]), 1.0, np.exp(-x0[-1])])
    r = ref.propagate(elements_of(setup), x0[st.RHO], x0[st.RHO_DOT], x0[st.OMEGA], x0[st.QUAT], moments,
                      setup.times, **kw)  # fmt: skip
    assert np.max(np.linalg.norm(truth.x[:, st.RHO] - r["rho"], axis=-1)) < 1e-3  # 1 mm
    assert np.max(np.linalg.norm(truth.x[:, st.RHO_DOT] - r["rho_dot"], axis=-1)) < 1e-6
    assert np.max(angle_between(truth.x[:, st.QUAT], r["q"])) < 1e-6  # 1 urad
    assert np.max(np.linalg.norm(truth.x[:, st.OMEGA] - r["omega"], axis=-1)) < 1e-9
    # and the perturbations are not negligible: the Keplerian truth is far from both
    kep = simulate_truth(dataclasses.replace(setup, perturbations=None))
    assert np.max(np.linalg.norm(kep.x[:, st.RHO] - r["rho"], axis=-1)) > 0.05


def test_alpha_is_the_time_derivative_of_omega():
    setup = setup_from(**LEO, truth_model=MODELS["j2+gg"][0])
    x0 = setup.x0
    moments = np.array([np.exp(x0[-2]), 1.0, np.exp(-x0[-1])])
    truth = simulate_truth(setup)
    k = 37
    h = 0.05  # central-difference truncation ~ h^2/6 |d3 omega/dt3| ~ 1e-9 rad/s^2 for this 2.6 deg/s tumble
    tt = np.array([0.0, truth.t[k] - h, truth.t[k] + h])
    r = ref.propagate(elements_of(setup), x0[st.RHO], x0[st.RHO_DOT], x0[st.OMEGA], x0[st.QUAT], moments, tt,
                      j2=True, gg=True)  # fmt: skip
    fd = (r["omega"][2] - r["omega"][1]) / (2 * h)
    assert np.abs(fd).max() > 1e-4
    np.testing.assert_allclose(truth.alpha[k], fd, atol=3e-9)


def test_no_perturbations_reproduce_the_keplerian_relative_truth():
    setup = setup_from(**ECCENTRIC, truth_model={})
    p = simulate_truth(setup)
    k = simulate_truth(dataclasses.replace(setup, perturbations=None))
    assert np.max(np.abs(p.x[:, st.RHO] - k.x[:, st.RHO])) < 1e-6
    assert np.max(np.abs(p.x[:, st.OMEGA] - k.x[:, st.OMEGA])) < 1e-11
    np.testing.assert_allclose(p.alpha, k.alpha, atol=1e-11)
    np.testing.assert_allclose(p.nu_dot, k.nu_dot, rtol=1e-10)


def test_j2_is_the_gradient_of_its_potential():
    r = np.array([[4.1e6, -3.3e6, 4.4e6], [7.0e6, 0.0, 0.0], [1e5, 2e5, 6.9e6]])
    expected = np.array([ref.gravity(v, True) - ref.gravity(v, False) for v in r])
    np.testing.assert_allclose(perturbed.accel_j2(r), expected, rtol=1e-10)


def test_osculating_elements_round_trip_and_filter_orbit():
    o = Orbit(a=7.2e6, e=0.07, i=0.6, raan=1.1, argp=-2.0, nu0=0.4)
    rv = elements_to_rv(o, np.array([0.4, 2.0]))
    el = perturbed.osculating_elements(rv[0], rv[1], o.mu)
    np.testing.assert_allclose(el["a"], o.a, rtol=1e-12)
    np.testing.assert_allclose(el["e"], o.e, rtol=1e-10)
    np.testing.assert_allclose([el["i"][0], el["raan"][0], el["argp"][0]], [o.i, o.raan, o.argp - 0.0], atol=1e-10)
    np.testing.assert_allclose(np.angle(np.exp(1j * el["nu"])), [0.4, 2.0], atol=1e-10)
    # the filter's orbit at t: its Keplerian kinematics at t are the osculating ones
    lk = leader_kinematics(o, 500.0)
    rl, vl = elements_to_rv(o, lk.nu)
    f = filter_orbit_at(np.concatenate([rl, vl]), 500.0, o.mu)
    lf = leader_kinematics(f, 500.0)
    np.testing.assert_allclose([lf.r, lf.nu_dot, lf.nu_ddot], [lk.r, lk.nu_dot, lk.nu_ddot], rtol=1e-9)


def test_batch_first():
    setup = setup_from(**LEO, truth_model=MODELS["j2+gg"][0])
    x0 = np.stack([setup.x0, setup.x0])
    x0[1, st.RHO] += [1.0, -2.0, 0.5]
    t = setup.times[:11]
    xb, ab, _ = perturbed_relative(setup, x0, t)
    x1, a1, _ = perturbed_relative(setup, x0[1:], t)
    assert xb.shape == (2, 11, x0.shape[1])
    np.testing.assert_allclose(xb[1], x1[0], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(ab[1], a1[0], rtol=1e-6, atol=1e-13)
    assert np.linalg.norm(qt.normalize(xb[..., st.QUAT]) - xb[..., st.QUAT]) < 1e-9
