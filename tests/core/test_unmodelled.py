"""Bounds on the perturbed truth's unmodelled motion (core/unmodelled.py) against the truth's own force models."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.common import Q_continuous_white_noise

from stereopose_mc.core import quaternion as qt
from stereopose_mc.core import unmodelled as um
from stereopose_mc.core.perturbed import J2, MU, R_EARTH, Perturbations, accel_drag, accel_j2, gravity_gradient_torque

R = 6.8e6  # m


def on_orbit(r: float, inc: float, u: np.ndarray) -> np.ndarray:
    """Positions ``(n, 3)`` at argument of latitude ``u`` on a circle of radius ``r`` and inclination ``inc``."""
    return r * np.stack([np.cos(u), np.sin(u) * np.cos(inc), np.sin(u) * np.sin(inc)], axis=-1)


@pytest.mark.parametrize("inc_deg", [0.0, 15.0, 50.0, 90.0, 165.0])
def test_j2_differential_bounds_and_meets_the_actual_difference(inc_deg):
    """The difference of a_J2 at two points ``rho`` apart, over the orbit's latitudes and every direction, stays
    under the bound and reaches it (to 1 %) in the worst direction (the Hessian's eigenvector)."""
    inc, rho = np.radians(inc_deg), 60.0
    bound = um.j2_differential(R, abs(np.sin(inc)), rho)
    rng = np.random.default_rng(1)
    r = on_orbit(R, inc, np.linspace(0.0, 2.0 * np.pi, 181))
    worst = 0.0
    for p in r:
        dirs = rng.standard_normal((60, 3))
        # the J2 potential's Hessian by finite differences of the truth's a_J2, for its worst direction
        h = 1.0
        G = np.stack([(accel_j2(p + h * e) - accel_j2(p - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
        w, V = np.linalg.eigh(0.5 * (G + G.T))
        dirs = np.vstack([dirs, V.T])
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        diff = np.linalg.norm(accel_j2(p + rho * dirs) - accel_j2(p), axis=1)
        worst = max(worst, diff.max())
    assert worst <= bound * (1 + 1e-3)
    assert worst >= 0.99 * bound


def test_j2_gradient_constant_equator_and_pole():
    """c = 6 on the equator (radial: d/dr of 3 J2 mu R^2 / r^4 ... x 3/2) and 12 over a pole (d/dz of 3 J2 mu R^2 / z^4)."""
    assert um.j2_gradient_constant(0.0) == pytest.approx(6.0, rel=1e-12)
    assert um.j2_gradient_constant(1.0) == pytest.approx(12.0, rel=1e-12)
    # at the pole a_z = 3 J2 mu R^2 / z^4 exactly, so its z-derivative is -12 J2 mu R^2 / z^5
    z = 7.0e6
    d = accel_j2(np.array([0.0, 0.0, z + 1.0]))[2] - accel_j2(np.array([0.0, 0.0, z - 1.0]))[2]
    assert abs(d / 2.0) == pytest.approx(12.0 * J2 * MU * R_EARTH**2 / z**5, rel=1e-6)


def test_gravity_gradient_alpha_by_hand():
    """Box inertia 11.25, 13, 6.25 kg m^2 at r = 7000 km: 3 mu / (2 r^3) = 1.74315062e-6 rad/s^2 times
    sqrt(0.6^2 + (5/13)^2 + 0.28^2) = 0.76572122 (the three (I_j - I_k) / I_i) = 1.33476743e-6 rad/s^2."""
    J = np.array([11.25, 13.0, 6.25])
    assert um.gravity_gradient_alpha(7.0e6, J) == pytest.approx(1.33476743e-6, rel=1e-8)
    # and it bounds the truth's torque over attitudes (the per-axis maxima sit at 45 deg between two axes)
    rng = np.random.default_rng(2)
    r_b = 7.0e6 * qt.normalize(rng.standard_normal((20000, 3)))
    alpha = np.linalg.norm(gravity_gradient_torque(r_b, J) / J, axis=1)
    assert alpha.max() <= 1.33476743e-6
    s = np.sqrt(0.5)
    per_axis = np.abs(gravity_gradient_torque(7.0e6 * np.array([[0, s, s], [s, 0, s], [s, s, 0]]), J) / J).max(axis=1)
    assert per_axis == pytest.approx(1.74315062e-6 * np.array([0.6, 5 / 13, 0.28]), rel=1e-8)


def test_drag_differential_bounds_the_actual_difference():
    """Two spacecraft ``rho`` apart at perigee with different ballistic coefficients: the difference of the truth's
    drag stays under the bound, which is not loose by more than the relative-speed margin."""
    p = Perturbations(drag=True, ballistic_leader=80.0, ballistic_target=120.0)
    a, e = 6.9e6, 0.01
    r_p = a * (1 - e)
    v_p = np.sqrt(MU * (2 / r_p - 1 / a))
    rho, rho_dot = 100.0, 0.1
    rng = np.random.default_rng(3)
    rL = on_orbit(r_p, 0.9, np.zeros(1))[0]
    vL = v_p * on_orbit(1.0, 0.9, np.full(1, np.pi / 2))[0]
    d = qt.normalize(rng.standard_normal((500, 3)))
    dv = qt.normalize(rng.standard_normal((500, 3)))
    n = v_p / r_p
    aL = accel_drag(rL, vL, p.ballistic_leader, p)
    aT = accel_drag(rL + rho * d, vL + rho_dot * dv + n * rho * np.cross([0, 0, 1.0], d), p.ballistic_target, p)
    diff = np.linalg.norm(aT - aL, axis=1)
    bound = um.drag_differential(r_p - rho, a, rho, rho_dot, p)
    assert diff.max() <= bound
    assert diff.max() >= 0.5 * bound


def test_white_acceleration_is_filterpy_q_diagonal():
    """Per-step variances of white noise of density a^2 dt: FilterPy's continuous white-noise Q, diagonal."""
    a, dt = 3e-7, 2.0
    Q = Q_continuous_white_noise(dim=2, dt=dt, spectral_density=a * a * dt)
    assert um.white_acceleration(a, dt) == pytest.approx((Q[0, 0], Q[1, 1]), rel=1e-14)


def test_unmodelled_without_truth_model_is_zero_and_flags_select():
    J = np.array([1.0, 2.0, 3.0])
    assert um.unmodelled(None, 7e6, 0.0, 0.5, 50.0, 0.1, J) == um.Unmodelled()
    u = um.unmodelled(Perturbations(j2=True), 7e6, 0.0, 0.5, 50.0, 0.1, J)
    assert u.j2 == pytest.approx(um.j2_differential(7e6 - 50.0, np.sin(0.5), 50.0))
    assert u.drag == 0.0 and u.gravity_gradient == 0.0
    u = um.unmodelled(Perturbations(gravity_gradient=True), 7e6, 0.1, 0.5, 50.0, 0.1, J)
    assert u.j2 == 0.0 and u.gravity_gradient == pytest.approx(um.gravity_gradient_alpha(7e6 * 0.9 - 50.0, J))


def test_bias_as_white_variance_keeps_the_mean_of_the_rows_consistent():
    """K rows with a bias beta and white noise sigma, treated as white noise of variance s^2: the mean's NEES
    (Monte Carlo over 20,000 draws) is 1 + K beta^2 / s^2: 26 with s = sigma, 1 with s^2 = sigma^2 +
    bias_as_white_variance(beta, K, 1) = sigma^2 + K beta^2."""
    from stereopose_mc.core.unmodelled import bias_as_white_variance

    rng = np.random.default_rng(3)
    K, beta, sigma = 100, 0.5, 1.0
    means = beta + sigma * rng.standard_normal((20000, K)).mean(axis=1)
    for s2, expected in ((sigma**2, 26.0), (sigma**2 + bias_as_white_variance(beta, K, axes=1), 1.0)):
        np.testing.assert_allclose(np.mean(means**2 / (s2 / K)), expected, rtol=0.03)
    assert bias_as_white_variance(0.3, 12) == pytest.approx(0.36, rel=1e-15)
