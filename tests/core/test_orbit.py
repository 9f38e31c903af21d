"""Leader orbit: Kepler's equation, the LVLH rates and the element -> state conversion."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as hs

from stereopose_mc.core.orbit import (
    MU_EARTH,
    Orbit,
    elements_to_rv,
    leader_kinematics,
    mean_to_true,
    true_to_mean,
)

ecc = hs.floats(0.0, 0.9, exclude_max=True)
SETTINGS = settings(max_examples=200, deadline=None)


@SETTINGS
@given(e=ecc, M=hs.floats(-40.0, 40.0))
def test_mean_true_mean_round_trip(e, M):
    """M -> nu -> M over several revolutions (Kepler solved by Newton to round-off)."""
    nu = mean_to_true(M, e)
    assert abs(true_to_mean(nu, e) - M) < 1e-12 * max(1.0, abs(M))
    # nu is in the same revolution as M (no wrap): the equation of the centre |nu - M| is below pi
    assert abs(nu - M) < np.pi + 1e-12


@SETTINGS
@given(e=ecc, nu=hs.floats(-40.0, 40.0))
def test_true_mean_true_round_trip(e, nu):
    """nu -> M -> nu; the conditioning is |dnu/dM| <= (1+e)^2 / (1-e^2)^1.5, hence the tolerance."""
    cond = (1.0 + e) ** 2 / (1.0 - e * e) ** 1.5
    assert abs(mean_to_true(true_to_mean(nu, e), e) - nu) < 4e-15 * cond * max(1.0, abs(nu))


@SETTINGS
@given(e=ecc, E=hs.floats(-np.pi, np.pi))
def test_kepler_equation_from_eccentric_anomaly(e, E):
    """Independent of the Newton solver: with M = E - e sin E, nu = 2 atan(sqrt((1+e)/(1-e)) tan(E/2))."""
    M = E - e * np.sin(E)
    nu_ref = 2.0 * np.arctan2(np.sqrt(1.0 + e) * np.sin(E / 2.0), np.sqrt(1.0 - e) * np.cos(E / 2.0))
    cond = (1.0 + e) ** 2 / (1.0 - e * e) ** 1.5
    assert abs(mean_to_true(M, e) - nu_ref) < 4e-15 * cond * 4.0
    assert abs(true_to_mean(nu_ref, e) - M) < 1e-14


def test_kinematics_match_finite_differences():
    """nu_dot, nu_ddot and r_dot are the time derivatives of nu(t), nu_dot(t) and r(t).

    Five-point central difference with h = 1 s (truncation ~ h^4 f^(5) / 30, negligible here).
    """
    orbit = Orbit(a=9000e3, e=0.25, i=0.3, raan=0.2, argp=1.0, nu0=2.0)
    t = np.linspace(0.0, 2.0 * 2 * np.pi / orbit.mean_motion, 97)  # two periods, through perigee and apogee
    h = 1.0
    lk = leader_kinematics(orbit, t)
    at = {j: leader_kinematics(orbit, t + j * h) for j in (-2, -1, 1, 2)}

    def deriv(name: str) -> np.ndarray:
        g = {j: getattr(v, name) for j, v in at.items()}
        return (8.0 * (g[1] - g[-1]) - (g[2] - g[-2])) / (12.0 * h)

    np.testing.assert_allclose(lk.nu_dot, deriv("nu"), rtol=1e-10)
    np.testing.assert_allclose(lk.r_dot, deriv("r"), rtol=0, atol=1e-8 * np.abs(lk.r_dot).max())
    np.testing.assert_allclose(lk.nu_ddot, deriv("nu_dot"), rtol=0, atol=1e-8 * np.abs(lk.nu_ddot).max())
    # nu is continuous over the two revolutions
    assert abs(lk.nu[0] - 2.0) < 1e-14 and abs(lk.nu[-1] - (2.0 + 4 * np.pi)) < 1e-12
    assert np.all(np.diff(lk.nu) > 0.0)


@SETTINGS
@given(
    a=hs.floats(6.6e6, 4.2e7),
    e=hs.floats(0.0, 0.8),
    i=hs.floats(0.0, np.pi),
    raan=hs.floats(-np.pi, np.pi),
    argp=hs.floats(-np.pi, np.pi),
    nu=hs.floats(-np.pi, np.pi),
)
def test_elements_to_rv_invariants(a, e, i, raan, argp, nu):
    """|h| = sqrt(mu p), v^2/2 - mu/r = -mu/(2a), h along the normal of (i, raan), and r, r_dot as the kinematics."""
    orbit = Orbit(a=a, e=e, i=i, raan=raan, argp=argp, nu0=nu)
    r, v = elements_to_rv(orbit)
    h = np.cross(r, v)
    rn = np.linalg.norm(r)
    assert abs(np.linalg.norm(h) / np.sqrt(MU_EARTH * orbit.p) - 1.0) < 1e-12
    energy = 0.5 * v @ v - MU_EARTH / rn
    assert abs(energy / (-MU_EARTH / (2.0 * a)) - 1.0) < 1e-11
    h_hat = np.array([np.sin(raan) * np.sin(i), -np.cos(raan) * np.sin(i), np.cos(i)])
    np.testing.assert_allclose(h / np.linalg.norm(h), h_hat, atol=1e-12)
    lk = leader_kinematics(orbit, 0.0)
    assert abs(rn / lk.r - 1.0) < 1e-12
    assert abs(r @ v / rn - lk.r_dot) < 1e-9 * np.linalg.norm(v)
    assert abs(np.linalg.norm(h) / rn**2 / lk.nu_dot - 1.0) < 1e-12


def test_initial_anomaly_keeps_its_revolution():
    """nu0 + 2 pi gives the same orbit with nu shifted by exactly 2 pi (nu0 is not wrapped)."""
    t = np.linspace(0.0, 5000.0, 11)
    base = leader_kinematics(Orbit(a=8000e3, e=0.3, nu0=2.0), t)
    turned = leader_kinematics(Orbit(a=8000e3, e=0.3, nu0=2.0 + 2 * np.pi), t)
    np.testing.assert_allclose(turned.nu - base.nu, 2 * np.pi, atol=1e-12)
    np.testing.assert_allclose(turned.nu_dot, base.nu_dot, rtol=1e-12)
