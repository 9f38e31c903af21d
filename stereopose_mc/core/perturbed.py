"""Perturbed truth in the inertial frame: J2, drag, gravity-gradient torque (batched).

Two spacecraft (leader ``L`` and target ``T``) and the target's attitude, in the
Earth-centred inertial frame ``I`` (z along the Earth's pole), state ``y (..., 19)``:

    y = [r_L (3), v_L (3), r_T (3), v_T (3), q_IT (4), w_T (3)]

with ``q_IT`` the target's attitude (scalar first, ``v^I = R(q_IT) v^T``) and ``w_T``
its inertial angular velocity in ``T``. Dynamics (SI):

    r'' = -mu r / |r|^3 + a_J2(r) + a_drag(r, v)
    a_J2 = -3/2 J2 mu R_E^2 / |r|^5 [x (1 - 5 z^2/r^2), y (1 - 5 z^2/r^2), z (3 - 5 z^2/r^2)]
    a_drag = -1/2 rho(h) |v_rel| v_rel / B,   v_rel = v - w_E x r,   B = m / (C_D A) (kg/m^2)
    rho(h) = rho_0 exp(-(h - h_0) / H),       h = |r| - R_E
    J w_T' = N - w_T x J w_T,   N = 3 mu / |r_T|^5 (r_b x J r_b),  r_b = R(q_IT)^T r_T
    q_IT' = 1/2 q_IT (x) [0, w_T]

The leader's LVLH frame (x = r/|r|, z = h/|h|, y = z x x) rotates with the angular
velocity, in its own components,

    w_F = [ |r| a_h / |h|,  0,  |h| / |r|^2 ]

where ``a_h`` is the leader's perturbing acceleration along ``z`` (Schaub & Junkins,
*Analytical Mechanics of Space Systems*, 14.2); it is ``[0, 0, nu_dot]`` on a Keplerian
orbit. Constants as in the issue: mu = 398600.4418 km^3/s^2, J2 = 1.08262668e-3,
R_E = 6378.137 km; the atmosphere co-rotates with the Earth (w_E = 7.292115e-5 rad/s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from . import quaternion as qt

Array = NDArray[np.float64]

MU = 3.986004418e14  # m^3/s^2
J2 = 1.08262668e-3
R_EARTH = 6378137.0  # m
OMEGA_EARTH = 7.292115e-5  # rad/s
N_STATE = 19
R_L, V_L, R_T, V_T, Q_IT, W_T = (slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 16), slice(16, 19))


@dataclass(frozen=True)
class Perturbations:
    """Which perturbations act on the truth, and their parameters (SI)."""

    j2: bool = False
    drag: bool = False
    ballistic_leader: float = 100.0  # kg/m^2, m / (C_D A)
    ballistic_target: float = 100.0
    density_ref: float = 3.614e-14  # kg/m^3 at h_ref (Vallado's exponential model, 700-800 km band)
    altitude_ref: float = 700e3  # m
    scale_height: float = 88667.0  # m
    gravity_gradient: bool = False


MAX_EVALUATIONS = 1_000_000  # right-hand sides per truth integration (a normal one needs < 1e5)

def accel_j2(r: Array) -> Array:
    """J2 acceleration ``(..., 3)`` at positions ``r (..., 3)`` (m/s^2)."""
    r2 = np.sum(r * r, axis=-1, keepdims=True)
    z2 = r[..., 2:3] ** 2 / r2
    k = -1.5 * J2 * MU * R_EARTH**2 / r2**2.5
    f = np.concatenate([1.0 - 5.0 * z2, 1.0 - 5.0 * z2, 3.0 - 5.0 * z2], axis=-1)
    return k * f * r


def density(r: Array, p: Perturbations) -> Array:
    """Exponential atmosphere ``(...)`` (kg/m^3) at positions ``r (..., 3)``."""
    h = np.linalg.norm(r, axis=-1) - R_EARTH
    return p.density_ref * np.exp(-(h - p.altitude_ref) / p.scale_height)


def accel_drag(r: Array, v: Array, ballistic: float, p: Perturbations) -> Array:
    """Drag ``-1/2 rho |v_rel| v_rel / B`` ``(..., 3)`` in a co-rotating atmosphere."""
    v_rel = v - qt.cross(np.array([0.0, 0.0, OMEGA_EARTH]), r)
    s = np.linalg.norm(v_rel, axis=-1, keepdims=True)
    return -0.5 * density(r, p)[..., None] * s * v_rel / ballistic


def perturbing_accel(r: Array, v: Array, ballistic: float, p: Perturbations) -> Array:
    """Everything but the central term: ``a_J2 + a_drag`` ``(..., 3)``."""
    a = accel_j2(r) if p.j2 else np.zeros_like(r)
    if p.drag:
        a = a + accel_drag(r, v, ballistic, p)
    return a


def gravity_gradient_torque(r_b: Array, J: Array) -> Array:
    """``3 mu / |r|^5 (r_b x J r_b)`` ``(..., 3)`` with ``J`` the principal moments ``(..., 3)``."""
    r2 = np.sum(r_b * r_b, axis=-1, keepdims=True)
    return 3.0 * MU / r2**2.5 * qt.cross(r_b, J * r_b)


def rhs(y: Array, J: Array, p: Perturbations) -> Array:
    """``dy/dt (..., 19)`` of the state above; ``J (..., 3)`` the target's principal moments."""
    rl, vl, rt, vt, q, w = y[..., R_L], y[..., V_L], y[..., R_T], y[..., V_T], y[..., Q_IT], y[..., W_T]

    def acc(r, v, b):
        return -MU * r / np.linalg.norm(r, axis=-1, keepdims=True) ** 3 + perturbing_accel(r, v, b, p)

    N = np.zeros_like(w)
    if p.gravity_gradient:
        r_b = np.einsum("...ji,...j->...i", qt.dcm(q), rt)  # R(q)^T r_T
        N = gravity_gradient_torque(r_b, J)
    w_dot = (N - qt.cross(w, J * w)) / J
    w4 = np.concatenate([np.zeros_like(w[..., :1]), w], axis=-1)
    q_dot = 0.5 * qt.multiply(q, w4)
    return np.concatenate([vl, acc(rl, vl, p.ballistic_leader), vt, acc(rt, vt, p.ballistic_target), q_dot, w_dot],
                          axis=-1)  # fmt: skip


def lvlh_axes(r: Array, v: Array) -> Array:
    """``R_IL (..., 3, 3)``: columns the LVLH x (radial), y, z (orbit normal) axes in ``I``."""
    x = r / np.linalg.norm(r, axis=-1, keepdims=True)
    h = qt.cross(r, v)
    z = h / np.linalg.norm(h, axis=-1, keepdims=True)
    return np.stack([x, qt.cross(z, x), z], axis=-1)


def lvlh_rate(r: Array, v: Array, a_pert: Array) -> Array:
    """``w_F = [|r| a_h / |h|, 0, |h| / |r|^2]`` ``(..., 3)`` of the LVLH frame, in its own axes."""
    h = qt.cross(r, v)
    hn = np.linalg.norm(h, axis=-1)
    rn = np.linalg.norm(r, axis=-1)
    a_h = np.sum(a_pert * h, axis=-1) / hn
    return np.stack([rn * a_h / hn, np.zeros_like(rn), hn / rn**2], axis=-1)


def propagate(y0: Array, t: Array, J: Array, p: Perturbations, rtol: float = 1e-12, dense: bool = False):
    """Integrate ``y0 (B, 19)`` (trial axis first) through the times ``t``; ``(B, K+1, 19)``.

    DOP853 on the flattened batch, absolute tolerances of 1e-6 m, 1e-9 m/s, 1e-14
    (quaternion) and 1e-15 rad/s scaled by ``rtol / 1e-12``. With ``dense`` also returns
    the continuous solution ``sol(t) -> (B, 19)``.
    """
    y0 = np.asarray(y0, dtype=float)
    B = y0.shape[0]
    J = np.broadcast_to(np.asarray(J, dtype=float), (B, 3))
    unit = np.concatenate([np.full(3, 1e-6), np.full(3, 1e-9), np.full(3, 1e-6), np.full(3, 1e-9),
                           np.full(4, 1e-14), np.full(3, 1e-15)])  # fmt: skip
    atol = np.tile(unit * (rtol / 1e-12), B)

    calls = [0]

    def f(_t, yy):
        calls[0] += 1
        if calls[0] > MAX_EVALUATIONS:  # a stiff truth (e.g. an absurd drag) would integrate for hours
            raise RuntimeError(f"perturbed truth integration: more than {MAX_EVALUATIONS} evaluations")
        return rhs(yy.reshape(B, N_STATE), J, p).reshape(-1)

    from scipy.integrate import solve_ivp  # only perturbed truths need it here

    sol = solve_ivp(f, (t[0], t[-1]), y0.reshape(-1), method="DOP853", t_eval=t, rtol=rtol, atol=atol,
                    dense_output=dense)  # fmt: skip
    if not sol.success:  # pragma: no cover - DOP853 on a smooth problem
        raise RuntimeError(f"perturbed truth integration failed: {sol.message}")
    Y = np.moveaxis(sol.y.reshape(B, N_STATE, -1), -1, 1)
    if not dense:
        return Y
    return Y, (lambda tt: sol.sol(tt).reshape(B, N_STATE))


def osculating_elements(r: Array, v: Array, mu: float = MU) -> dict[str, Array]:
    """Classical elements ``a, e, i, raan, argp, nu`` (m, rad) of inertial states ``(..., 3)``.

    Vallado, *Fundamentals of Astrodynamics*, algorithm 9 (RV2COE), for non-circular,
    non-equatorial orbits; on an equatorial orbit ``raan = 0`` and ``argp`` is measured
    from ``x``; on a circular orbit ``argp = 0`` and ``nu`` is the argument of latitude.
    """
    rn = np.linalg.norm(r, axis=-1)
    v2 = np.sum(v * v, axis=-1)
    h = qt.cross(r, v)
    hn = np.linalg.norm(h, axis=-1)
    nvec = qt.cross(np.array([0.0, 0.0, 1.0]), h)
    nn = np.linalg.norm(nvec, axis=-1)
    evec = ((v2 - mu / rn)[..., None] * r - np.sum(r * v, axis=-1)[..., None] * v) / mu
    e = np.linalg.norm(evec, axis=-1)
    a = 1.0 / (2.0 / rn - v2 / mu)
    i = np.arccos(np.clip(h[..., 2] / hn, -1.0, 1.0))
    eq = nn < 1e-12 * hn
    circ = e < 1e-12
    nx = np.where(eq, 1.0, nvec[..., 0] / np.where(eq, 1.0, nn))
    ny = np.where(eq, 0.0, nvec[..., 1] / np.where(eq, 1.0, nn))
    raan = np.where(eq, 0.0, np.arctan2(ny, nx))
    nhat = np.stack([nx, ny, np.zeros_like(nx)], axis=-1)
    hhat = h / hn[..., None]

    def angle(u, w):  # angle from u to w, positive about h
        return np.arctan2(np.sum(qt.cross(u, w) * hhat, axis=-1), np.sum(u * w, axis=-1))

    ehat = np.where(circ[..., None], nhat, evec / np.where(circ, 1.0, e)[..., None])
    argp = np.where(circ, 0.0, angle(nhat, ehat))
    nu = angle(ehat, r / rn[..., None])
    return {"a": a, "e": e, "i": i, "raan": raan, "argp": argp, "nu": nu}
