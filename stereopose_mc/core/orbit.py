"""Leader orbit: Keplerian elements to the LVLH kinematics the relative dynamics need.

The leader is on an unperturbed Keplerian orbit known to the filter. With
``p = a (1 - e^2)``:

    r_L = p / (1 + e cos nu)
    nu_dot = sqrt(mu / p^3) (1 + e cos nu)^2
    r_dot_L = sqrt(mu / p) e sin nu
    nu_ddot = -2 r_dot_L nu_dot / r_L

``nu(t)`` comes from Kepler's equation solved by Newton iteration to round-off, so
truth and filter share the same, exact leader motion. SI units throughout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

MU_EARTH = 3.986004418e14  # m^3/s^2

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Orbit:
    """Keplerian elements of the leader (SI: m and rad)."""

    a: float
    e: float
    i: float = 0.0
    raan: float = 0.0
    argp: float = 0.0
    nu0: float = 0.0
    mu: float = MU_EARTH

    @property
    def p(self) -> float:
        return self.a * (1.0 - self.e**2)

    @property
    def mean_motion(self) -> float:
        return float(np.sqrt(self.mu / self.a**3))


@dataclass(frozen=True)
class LeaderKinematics:
    """Leader quantities at times ``t`` (arrays of ``t``'s shape)."""

    t: Array
    nu: Array
    r: Array
    r_dot: Array
    nu_dot: Array
    nu_ddot: Array


def true_to_mean(nu: ArrayLike, e: float) -> Array:
    """Mean anomaly of true anomaly ``nu`` (rad), continuous across revolutions.

    The whole revolutions in ``nu`` are kept: ``M(nu + 2 pi k) = M(nu) + 2 pi k``.
    """
    nu = np.asarray(nu, dtype=float)
    revs = np.floor((nu + np.pi) / (2.0 * np.pi))
    nuw = nu - 2.0 * np.pi * revs
    E = 2.0 * np.arctan2(np.sqrt(1.0 - e) * np.sin(nuw / 2.0), np.sqrt(1.0 + e) * np.cos(nuw / 2.0))
    return E - e * np.sin(E) + 2.0 * np.pi * revs


def mean_to_true(M: ArrayLike, e: float, tol: float = 1e-15, max_iter: int = 50) -> Array:
    """True anomaly from mean anomaly by Newton's method on Kepler's equation.

    The result is continuous in ``M`` (no wrap to [-pi, pi)): the number of whole
    revolutions in ``M`` is kept.
    """
    M = np.asarray(M, dtype=float)
    revs = np.floor((M + np.pi) / (2.0 * np.pi))
    Mw = M - 2.0 * np.pi * revs
    E = np.where(e < 0.8, Mw, np.pi * np.sign(Mw))
    for _ in range(max_iter):
        dE = (E - e * np.sin(E) - Mw) / (1.0 - e * np.cos(E))
        E = E - dE
        if np.all(np.abs(dE) < tol):
            break
    nu = 2.0 * np.arctan2(np.sqrt(1.0 + e) * np.sin(E / 2.0), np.sqrt(1.0 - e) * np.cos(E / 2.0))
    return nu + 2.0 * np.pi * revs


def leader_kinematics(orbit: Orbit, t: ArrayLike) -> LeaderKinematics:
    """``nu, r_L, r_dot_L, nu_dot, nu_ddot`` at times ``t`` (s since epoch)."""
    t = np.asarray(t, dtype=float)
    e, mu, p = orbit.e, orbit.mu, orbit.p
    M = true_to_mean(orbit.nu0, e) + orbit.mean_motion * t
    nu = mean_to_true(M, e)
    c = 1.0 + e * np.cos(nu)
    r = p / c
    nu_dot = np.sqrt(mu / p**3) * c**2
    r_dot = np.sqrt(mu / p) * e * np.sin(nu)
    nu_ddot = -2.0 * r_dot * nu_dot / r
    return LeaderKinematics(t=t, nu=nu, r=r, r_dot=r_dot, nu_dot=nu_dot, nu_ddot=nu_ddot)


def elements_to_rv(orbit: Orbit, nu: ArrayLike | None = None) -> tuple[Array, Array]:
    """Inertial position and velocity (m, m/s) of the leader at true anomaly ``nu``."""
    nu = orbit.nu0 if nu is None else nu
    nu = np.asarray(nu, dtype=float)
    p, e, mu = orbit.p, orbit.e, orbit.mu
    r = p / (1.0 + e * np.cos(nu))
    r_pf = np.stack([r * np.cos(nu), r * np.sin(nu), np.zeros_like(nu)], axis=-1)
    v_pf = np.sqrt(mu / p) * np.stack([-np.sin(nu), e + np.cos(nu), np.zeros_like(nu)], axis=-1)
    R = perifocal_to_inertial(orbit)
    return r_pf @ R.T, v_pf @ R.T


def perifocal_to_inertial(orbit: Orbit) -> Array:
    """Rotation matrix R3(-raan) R1(-i) R3(-argp) from perifocal to inertial axes."""
    cO, sO = np.cos(orbit.raan), np.sin(orbit.raan)
    ci, si = np.cos(orbit.i), np.sin(orbit.i)
    cw, sw = np.cos(orbit.argp), np.sin(orbit.argp)
    return np.array(
        [
            [cO * cw - sO * sw * ci, -cO * sw - sO * cw * ci, sO * si],
            [sO * cw + cO * sw * ci, -sO * sw + cO * cw * ci, -cO * si],
            [sw * si, cw * si, ci],
        ]
    )
