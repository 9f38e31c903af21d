"""Simplified vs Segal-Gurfil coupled feature-point model (stereopose_mc.studies.coupled)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from stereopose_mc.config import load_scenario
from stereopose_mc.config.resolve import setup_of
from stereopose_mc.core import dynamics
from stereopose_mc.core import state as st
from stereopose_mc.core.orbit import leader_kinematics
from stereopose_mc.studies import coupled as cp
from stereopose_mc.studies.dynamics_study import feature_study, integrate
from scenarios import CONFIGS


@pytest.fixture(scope="module")
def caseB():
    s = setup_of(load_scenario(CONFIGS / "caseB.yaml"))
    N = s.n_points
    return s.orbit, s.x0[: cp.simplified_size(N)], s.x0[st.k_slice(N)], s.x0


def test_sizes():
    assert [cp.simplified_size(n) for n in (1, 5, 100)] == [16, 28, 313]
    assert [cp.coupled_size(n) for n in (1, 5, 100)] == [22, 58, 913]
    assert cp.n_points_coupled(58) == 5 and cp.n_points_simplified(28) == 5
    with pytest.raises(ValueError):
        cp.n_points_coupled(28)


def test_simplified_rhs_is_the_package_model(caseB):
    """The 13+3N model equals ``core.dynamics.f`` on the 15+3N state without ``k``."""
    orbit, s0, k, x0 = caseB
    lk = leader_kinematics(orbit, 123.0)
    ref = dynamics.f(x0, lk.r, lk.nu_dot, lk.nu_ddot, orbit.mu)
    got = cp.simplified_rhs(s0, lk.r, lk.nu_dot, lk.nu_ddot, k, orbit.mu)
    assert np.array_equal(got, ref[: s0.size])


def test_rigid_body_terms_match_finite_differences_of_D_P(caseB):
    """``(D P)'' = w' x DP + w x (w x DP)`` against central differences of ``D(q(t)) P`` along the ODE."""
    orbit, s0, k, _ = caseB
    s = s0.copy()
    s[cp.OMEGA] = np.array([0.02, -0.03, 0.05])  # faster than case B so the term is well above round-off
    h = 0.5
    t = np.array([0.0, h, 2 * h])
    Y, _ = integrate(cp.simplified_rhs, s, t, orbit, 1e-13, k=k, mu=orbit.mu)
    N = cp.n_points_simplified(s.size)
    PL = cp.points_in_L(Y, N)
    fd = (PL[2] - 2 * PL[1] + PL[0]) / h**2
    lk = leader_kinematics(orbit, h)
    w_dot = cp.simplified_rhs(Y[1], lk.r, lk.nu_dot, lk.nu_ddot, k, orbit.mu)[cp.OMEGA]
    _, be = cp.constraint_terms(Y[1, cp.OMEGA], w_dot, PL[1])
    assert np.allclose(fd, be, rtol=1e-4, atol=1e-4 * np.abs(be).max())


def test_consistent_coupled_state_gives_the_rigid_body_acceleration(caseB):
    """At ``rho_i = rho_0 + DP``, ``rho_i' = rho_0' + w x DP``: ``rho_i'' = rho_0'' + w' x DP + w x (w x DP)``."""
    orbit, s0, k, _ = caseB
    c0 = cp.coupled_initial(s0)
    lk = leader_kinematics(orbit, 0.0)
    cd = cp.coupled_rhs(c0, lk.r, lk.nu_dot, lk.nu_ddot, k, orbit.mu)
    N = cp.n_points_coupled(c0.size)
    acc = cd[cp.simplified_size(N) + 3 * N :].reshape(N, 3)
    PL = cp.points_in_L(s0, N)
    w, wd = s0[cp.OMEGA], cd[cp.OMEGA]
    expected = cd[None, cp.RHO_DOT] + np.cross(wd, PL) + np.cross(w, np.cross(w, PL))
    # rho_0'' ~ 1e-5 m/s^2 comes out of a ~8 m/s^2 cancellation: agreement to ~1e-15 absolute
    assert np.abs(acc - expected).max() < 1e-13
    # velocities of the points are carried as states
    i0 = cp.simplified_size(N)
    assert np.array_equal(cd[i0 : i0 + 3 * N], c0[i0 + 3 * N :])


def test_coupled_rhs_is_batched(caseB):
    orbit, s0, k, _ = caseB
    rng = np.random.default_rng(1)
    c = cp.coupled_initial(s0) + 1e-3 * rng.standard_normal((2, 3, cp.coupled_size(5)))
    lk = leader_kinematics(orbit, np.array([[0.0, 10.0, 20.0], [30.0, 40.0, 50.0]]))
    out = cp.coupled_rhs(c, lk.r, lk.nu_dot, lk.nu_ddot, k, orbit.mu)
    assert out.shape == c.shape
    one = cp.coupled_rhs(c[1, 2], lk.r[1, 2], lk.nu_dot[1, 2], lk.nu_ddot[1, 2], k, orbit.mu)
    assert np.allclose(out[1, 2], one, rtol=1e-14, atol=1e-18)


def test_coupled_and_simplified_feature_trajectories_agree_on_caseB(caseB):
    """Over 600 s of case B, |rho_i,coupled - rho_i,simplified| is at the integration-error level,
    while the thesis's printed signs give a difference many orders of magnitude larger."""
    orbit, s0, k, _ = caseB
    t = np.linspace(0.0, 600.0, 121)
    fs = feature_study(orbit, s0, k, t, rtol=1e-11, rtol_reference=1e-13)
    diff = fs.difference.max()
    err = fs.integration_error.max()
    assert diff < 1e-8  # metres, over trajectories ~60 m from the leader with 1.5 m lever arms
    assert diff < 10.0 * err + 1e-12
    assert fs.printed_difference.max() > 1e-3
    # the points really move relative to the c.m. (the comparison is not trivial)
    offsets = fs.simplified - fs.cm[:, None, :]
    assert np.linalg.norm(offsets[-1] - offsets[0], axis=-1).max() > 0.05


def test_loose_tolerance_shows_the_comparison_is_sensitive(caseB):
    """With rtol 1e-5 the two models' integration errors differ visibly: the agreement above is not by construction."""
    orbit, s0, k, _ = caseB
    t = np.linspace(0.0, 600.0, 61)
    S, _ = integrate(cp.simplified_rhs, s0, t, orbit, 1e-5, k=k, mu=orbit.mu)
    C, _ = integrate(cp.coupled_rhs, cp.coupled_initial(s0), t, orbit, 1e-5, k=k, mu=orbit.mu)
    loose = np.abs(cp.simplified_features(S) - cp.coupled_features(C)).max()
    assert loose > 1e-7
