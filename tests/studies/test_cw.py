"""Clohessy-Wiltshire closed form and transition matrix (stereopose_mc.studies.cw)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from stereopose_mc.core.dynamics import translational_acceleration
from stereopose_mc.core.orbit import MU_EARTH, Orbit
from stereopose_mc.studies.cw import cw_intercept_velocity, cw_matrix, cw_propagate, cw_stm
from stereopose_mc.studies.dynamics_study import cw_case, scaling_study

A_LEO = 7170e3
N_LEO = float(np.sqrt(MU_EARTH / A_LEO**3))
S0 = np.array([10.0, 60.0, 10.0, 0.01, -0.0225, -0.01])


def test_closed_form_matches_numerical_integration_of_the_linear_ode():
    """``Phi(t) s0`` against DOP853 on ``s' = A s`` at rtol 1e-13, over 1.5 orbits."""
    t = np.linspace(0.0, 1.5 * 2 * np.pi / N_LEO, 301)
    A = cw_matrix(N_LEO)
    sol = solve_ivp(lambda _, s: A @ s, (t[0], t[-1]), S0, method="DOP853", t_eval=t, rtol=1e-13, atol=1e-15)
    closed = cw_propagate(S0, N_LEO, t)
    scale = np.abs(sol.y.T).max(axis=0)
    assert np.max(np.abs(closed - sol.y.T) / scale) < 1e-11


@pytest.mark.parametrize("t", [0.0, 1.0, 100.0, 2500.0, 6042.0, 20000.0])
def test_stm_equals_matrix_exponential(t):
    """``Phi(t) = expm(A t)`` to round-off (an independent closed form)."""
    Phi = cw_stm(N_LEO, t)
    E = expm(cw_matrix(N_LEO) * t)
    assert np.allclose(Phi, E, rtol=1e-11, atol=1e-11 * max(1.0, np.abs(E).max()))


@settings(max_examples=60, deadline=None)
@given(
    t1=hs.floats(-12000.0, 12000.0),
    t2=hs.floats(-12000.0, 12000.0),
    n=hs.floats(1e-4, 2e-3),
)
def test_stm_composition(t1, t2, n):
    """``Phi(t1 + t2) = Phi(t2) Phi(t1)`` and ``det Phi = 1`` (trace A = 0)."""
    P12 = cw_stm(n, t1 + t2)
    comp = cw_stm(n, t2) @ cw_stm(n, t1)
    scale = max(1.0, np.abs(comp).max(), np.abs(P12).max())
    assert np.max(np.abs(P12 - comp)) < 1e-9 * scale
    assert np.linalg.det(cw_stm(n, t1)) == pytest.approx(1.0, abs=1e-6)


def test_propagate_is_batched():
    s = np.stack([S0, 2.0 * S0, -S0])
    t = np.array([0.0, 10.0, 500.0])
    out = cw_propagate(s[None], N_LEO, t)
    assert out.shape == (1, 3, 3, 6)
    for b in range(3):
        assert np.allclose(out[0, b], cw_propagate(s[b], N_LEO, t), rtol=0, atol=0)
    assert np.array_equal(out[0, :, 0], s)


def test_cw_matrix_is_the_linearization_of_the_nonlinear_model():
    """``dg/d[rho, rho']`` at 0 on a circular orbit (central differences) equals ``A[3:]``."""
    r, nu_dot = A_LEO, N_LEO
    J = np.empty((3, 6))
    for j in range(6):
        h = 1e-3 if j < 3 else 1e-6
        e = np.zeros(6)
        e[j] = h
        gp = translational_acceleration(e[:3], e[3:], r, nu_dot, 0.0)
        gm = translational_acceleration(-e[:3], -e[3:], r, nu_dot, 0.0)
        J[:, j] = (gp - gm) / (2 * h)
    assert np.allclose(J, cw_matrix(N_LEO)[3:], rtol=1e-6, atol=1e-12)


def test_intercept_velocity_reaches_the_origin():
    v = cw_intercept_velocity(S0[:3], N_LEO, 80.0)
    s = cw_propagate(np.concatenate([S0[:3], v]), N_LEO, [80.0])[0]
    assert np.abs(s[:3]).max() < 1e-10
    # for 80 s << 1/n the intercept is almost a straight line: v ~ -rho0 / t_f
    assert np.allclose(v, -S0[:3] / 80.0, rtol=0.2, atol=0.05)


def test_nonlinear_minus_cw_is_quadratic_in_separation_on_a_circular_orbit():
    """Doubling the whole relative state multiplies max |rho_NL - rho_CW| by 4 (to 0.5 %)."""
    orbit = Orbit(a=A_LEO, e=0.0)
    t = np.linspace(0.0, 2000.0, 201)
    f, d, slope = scaling_study(orbit, S0, t, (1.0, 2.0, 4.0), rtol=1e-12)
    assert d[1] / d[0] == pytest.approx(4.0, rel=5e-3)
    assert d[2] / d[1] == pytest.approx(4.0, rel=5e-3)
    assert slope == pytest.approx(2.0, abs=5e-3)
    # and the CW error is small next to the motion itself (close-proximity regime)
    case = cw_case("circular", orbit, S0, t, rtol=1e-12)
    assert case.difference.max() < 1e-3 * np.linalg.norm(case.nonlinear[:, :3], axis=-1).max()


def test_eccentric_orbit_breaks_cw_at_first_order():
    """On e = 0.05 the CW error is of order e |rho| (not quadratic): far above the circular one."""
    t = np.linspace(0.0, 2000.0, 201)
    circ = cw_case("c", Orbit(a=A_LEO, e=0.0), S0, t, 1e-12).difference.max()
    ecc = cw_case("e", Orbit(a=A_LEO, e=0.05), S0, t, 1e-12).difference.max()
    assert ecc > 100.0 * circ
    ecc_half = cw_case("e", Orbit(a=A_LEO, e=0.05), 0.5 * S0, t, 1e-12).difference.max()
    assert ecc_half / ecc == pytest.approx(0.5, rel=0.02)  # linear in the separation
