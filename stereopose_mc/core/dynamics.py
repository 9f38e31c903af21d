"""Process model ``x_dot = f(x, t)`` of the relative state and its integration.

Translation of the target's centre of mass in the leader's LVLH frame (docs/model.md):

    x'' =  2 nu' y' + nu'' y + nu'^2 x - mu (r_L + x) / R^3 + mu / r_L^2
    y'' = -2 nu' x' - nu'' x + nu'^2 y - mu y / R^3
    z'' = -mu z / R^3,          R = sqrt((r_L + x)^2 + y^2 + z^2)

Rotation of a torque-free target (Euler in ``T``), relative angular velocity in ``L``:

    w_T     = D^T (w + w_L)
    w_T'    = I^-1 (-w_T x I w_T)
    w'      = D w_T' - w_L' - w_L x w
    q'      = 1/2 Q(q) D^T w

with ``w_L = [0, 0, nu']``, ``w_L' = [0, 0, nu'']``; ``P_i' = 0`` and ``k' = 0``.
Every function takes a leading batch axis ``(..., n)``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import quaternion as qt
from . import state as st
from .orbit import MU_EARTH, Orbit, leader_kinematics

Array = NDArray[np.float64]


def translational_acceleration(rho: Array, rho_dot: Array, r_L, nu_dot, nu_ddot, mu: float = MU_EARTH) -> Array:
    """Relative acceleration ``rho''`` (``...,3``) in ``L`` (nonlinear, eccentric leader)."""
    x, y, z = np.moveaxis(rho, -1, 0)
    vx, vy, _ = np.moveaxis(rho_dot, -1, 0)
    R3 = ((r_L + x) ** 2 + y * y + z * z) ** 1.5
    ax = 2.0 * nu_dot * vy + nu_ddot * y + nu_dot**2 * x - mu * (r_L + x) / R3 + mu / r_L**2
    ay = -2.0 * nu_dot * vx - nu_ddot * x + nu_dot**2 * y - mu * y / R3
    az = -mu * z / R3
    return np.stack([ax, ay, az], axis=-1)


def omega_leader(nu_dot, shape=()) -> Array:
    """``w_L = [0, 0, nu']`` broadcast to ``shape + (3,)``."""
    w = np.zeros(np.broadcast_shapes(np.shape(nu_dot), shape) + (3,))
    w[..., 2] = nu_dot
    return w


def euler_body_rate(w_T: Array, inertia: Array, torque_T: Array | None = None) -> Array:
    """``w_T' = I^-1 (N - w_T x I w_T)`` for principal moments ``inertia (...,3)``."""
    Iw = inertia * w_T
    rhs = -qt.cross(w_T, Iw)
    if torque_T is not None:
        rhs = rhs + torque_T
    return rhs / inertia


def rotational_rates(omega: Array, q: Array, k: Array, nu_dot, nu_ddot) -> tuple[Array, Array]:
    """``(w', q')`` of the relative rotation, both in the layout of the state."""
    D = qt.dcm(q)
    wL = omega_leader(nu_dot, omega.shape[:-1])
    w_T = qt.rmatvec(D, omega + wL)
    w_T_dot = euler_body_rate(w_T, st.inertia_diag(k))
    omega_dot = qt.matvec(D, w_T_dot) - qt.cross(wL, omega)
    omega_dot[..., 2] -= nu_ddot
    w_rel_T = w_T - qt.rmatvec(D, wL)
    q_dot = 0.5 * qt.multiply(q, np.concatenate([np.zeros(w_rel_T.shape[:-1] + (1,)), w_rel_T], axis=-1))
    return omega_dot, q_dot


def f(x: Array, r_L, nu_dot, nu_ddot, mu: float = MU_EARTH) -> Array:
    """Time derivative of the state ``x (..., n)`` given the leader's ``r_L, nu', nu''``."""
    N = st.n_points(x.shape[-1])
    ks = st.k_slice(N)
    xdot = np.zeros_like(x)
    xdot[..., st.RHO] = x[..., st.RHO_DOT]
    xdot[..., st.RHO_DOT] = translational_acceleration(x[..., st.RHO], x[..., st.RHO_DOT], r_L, nu_dot, nu_ddot, mu)
    w_dot, q_dot = rotational_rates(x[..., st.OMEGA], x[..., st.QUAT], x[..., ks], nu_dot, nu_ddot)
    xdot[..., st.OMEGA] = w_dot
    xdot[..., st.QUAT] = q_dot
    return xdot


def f_at(x: Array, t: float, orbit: Orbit) -> Array:
    """``f`` with the leader's kinematics evaluated at time ``t``."""
    lk = leader_kinematics(orbit, t)
    return f(x, lk.r, lk.nu_dot, lk.nu_ddot, orbit.mu)


def propagate(x: Array, t: float, dt: float, orbit: Orbit, substeps: int = 1) -> Array:
    """Integrate ``f`` from ``t`` to ``t + dt`` with ``substeps`` classical RK4 steps.

    The leader's kinematics are evaluated once for all the stage times (a shared time
    for every trial of the batch).
    """
    h = dt / substeps
    lk = leader_kinematics(orbit, t + 0.5 * h * np.arange(2 * substeps + 1))
    mu = orbit.mu

    def fk(y, i):
        return f(y, lk.r[i], lk.nu_dot[i], lk.nu_ddot[i], mu)

    for j in range(substeps):
        i = 2 * j
        k1 = fk(x, i)
        k2 = fk(x + 0.5 * h * k1, i + 1)
        k3 = fk(x + 0.5 * h * k2, i + 1)
        k4 = fk(x + h * k3, i + 2)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return x
