"""Feature-point dynamics: the simplified coupled model and the Segal-Gurfil coupled model.

Both describe the motion, in the leader's LVLH frame ``L``, of feature points ``P_i``
fixed in the target's body frame ``T`` (thesis section 2.4). ``P_i^L = D(q) P_i`` is the
point's offset from the target's centre of mass in ``L``, ``w`` the relative angular
velocity (in ``L``), ``g(rho, rho')`` the nonlinear relative acceleration of docs/model.md
(:func:`stereopose_mc.core.dynamics.translational_acceleration`).

**Simplified coupled model** (the package's, thesis eq. 2.44), state of size 13 + 3N:

    s = [rho_0 (3), rho_0' (3), w (3), q (4), P_1 ... P_N (3N)]
    rho_0'' = g(rho_0, rho_0'),   (w', q') from the attitude ODE,   P_i' = 0
    rho_i   = rho_0 + D(q) P_i        (evaluated after integration)

**Coupled model** (Segal-Gurfil, thesis eqs. 2.40-2.42), state of size 13 + 9N:

    c = [rho_0, rho_0', w, q, P_1 ... P_N, rho_1 ... rho_N (3N), rho_1' ... rho_N' (3N)]

where each feature point's position ``rho_i = [x_i, y_i, z_i]`` is integrated with its own
relative translational dynamics. With ``a = w x P^L``, ``b = w x (w x P^L)``,
``e = w' x P^L`` and ``d = rho_i - P^L``:

    x_i'' = b_x + e_x + 2 nu' (y_i' - a_y) + nu'' d_y + nu'^2 d_x - mu (r_L + d_x)/R^3 + mu/r_L^2
    y_i'' = b_y + e_y - 2 nu' (x_i' - a_x) - nu'' d_x + nu'^2 d_y - mu d_y / R^3
    z_i'' = b_z + e_z                                             - mu d_z / R^3
    R = |r_L e_x + d|

i.e. ``rho_i'' = g(rho_i - P^L, rho_i' - w x P^L) + w' x P^L + w x (w x P^L)``, which is
what substituting thesis eqs. 2.37-2.39 into the translational equations gives. The
attitude block is the package's (docs/model.md; the thesis's eq. 2.27 is replaced by its
correct form), ``w'`` enters the point equations. The c.m. block is kept so that both
models carry the same attitude and c.m. states (the thesis's case has ``P_0 = 0``).

Misprints in thesis eqs. 2.40-2.42, corrected here (``as_printed=True`` reproduces them,
for the study that shows they matter):

1. the centripetal bracket: the thesis writes ``w_y(w_x P_y - w_y P_x) + w_z(w_z P_x - w_x P_z)``
   for ``[w x (w x P)]_x`` (and cyclically for y, z); the second product's sign is wrong:
   ``[w x (w x P)]_x = w_y(w_x P_y - w_y P_x) - w_z(w_z P_x - w_x P_z)``;
2. the Coriolis corrections: the thesis writes ``y_i' - (w_z P_x + w_x P_z)`` and
   ``x_i' - (w_y P_z + w_z P_y)``; the components of ``w x P`` are
   ``(w x P)_y = w_z P_x - w_x P_z`` and ``(w x P)_x = w_y P_z - w_z P_y``;
3. eq. 2.9's ``+ mu (r_L + x)/R^3`` (docs/model.md) does not recur: eq. 2.40 prints the minus sign.
   The ``x_ij`` subscripts of eqs. 2.40-2.42 are read as ``x_i``. ``P_T^i`` is the point's
   offset in ``L``, i.e. ``D P_i`` with ``P_i`` the (constant) body-frame coordinates.

Every function takes leading batch axes (``...``) and keeps them; the leader quantities
``r_L, nu', nu''`` broadcast against them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..core import quaternion as qt
from ..core.dynamics import rotational_rates, translational_acceleration
from ..core.orbit import MU_EARTH
from ..core.state import OMEGA, POINTS0, QUAT, RHO, RHO_DOT

Array = NDArray[np.float64]

# the first 13 components are laid out as in the filter state (core.state)
BASE = POINTS0


def simplified_size(n_points: int) -> int:
    """``13 + 3N``."""
    return BASE + 3 * n_points


def coupled_size(n_points: int) -> int:
    """``13 + 9N``."""
    return BASE + 9 * n_points


def n_points_simplified(n: int) -> int:
    if n < BASE or (n - BASE) % 3:
        raise ValueError(f"a simplified state has 13 + 3N entries, got {n}")
    return (n - BASE) // 3


def n_points_coupled(n: int) -> int:
    if n < BASE or (n - BASE) % 9:
        raise ValueError(f"a coupled state has 13 + 9N entries, got {n}")
    return (n - BASE) // 9


def body_points(x: Array, n_points: int) -> Array:
    """Body-frame points ``P_i (..., N, 3)`` of a simplified or coupled state."""
    return x[..., BASE : BASE + 3 * n_points].reshape(x.shape[:-1] + (n_points, 3))


def points_in_L(x: Array, n_points: int) -> Array:
    """``P_i^L = D(q) P_i`` (``..., N, 3``)."""
    D = qt.dcm(x[..., QUAT])
    return np.einsum("...ij,...nj->...ni", D, body_points(x, n_points))


def simplified_rhs(x: Array, r_L, nu_dot, nu_ddot, k: Array, mu: float = MU_EARTH) -> Array:
    """``s'`` of the simplified model: ``[rho_0', g(rho_0, rho_0'), w', q', 0]``.

    ``k = [ln(Ix/Iy), ln(Iy/Iz)]`` fixes the target's inertia (not a state here).
    """
    x = np.asarray(x, dtype=float)
    xdot = np.zeros_like(x)
    xdot[..., RHO] = x[..., RHO_DOT]
    xdot[..., RHO_DOT] = translational_acceleration(x[..., RHO], x[..., RHO_DOT], r_L, nu_dot, nu_ddot, mu)
    kk = np.broadcast_to(np.asarray(k, dtype=float), x.shape[:-1] + (2,))
    w_dot, q_dot = rotational_rates(x[..., OMEGA], x[..., QUAT], kk, nu_dot, nu_ddot)
    xdot[..., OMEGA] = w_dot
    xdot[..., QUAT] = q_dot
    return xdot


def constraint_terms(omega: Array, omega_dot: Array, P_L: Array, as_printed: bool = False) -> tuple[Array, Array]:
    """Rigid-body terms of eqs. 2.40-2.42 for points ``P_L (..., N, 3)``.

    Returns ``(a, b + e)`` with ``a = w x P^L`` (the velocity offset in the Coriolis term) and
    ``b + e = w x (w x P^L) + w' x P^L`` (the acceleration offset). With ``as_printed`` the
    thesis's sign misprints (module docstring, items 1 and 2) are reproduced.
    """
    w = omega[..., None, :]
    a = np.cross(w, P_L)
    b = np.cross(w, a)
    e = np.cross(omega_dot[..., None, :], P_L)
    if as_printed:
        wx, wy, wz = np.moveaxis(w, -1, 0)
        Px, Py, Pz = np.moveaxis(P_L, -1, 0)
        b = np.stack(
            [
                wy * (wx * Py - wy * Px) + wz * (wz * Px - wx * Pz),
                wz * (wy * Pz - wz * Py) + wx * (wx * Py - wy * Px),
                wx * (wz * Px - wx * Pz) + wy * (wy * Pz - wz * Py),
            ],
            axis=-1,
        )
        a = np.stack([wy * Pz + wz * Py, wz * Px + wx * Pz, a[..., 2]], axis=-1)
    return a, b + e


def feature_acceleration(
    rho_i: Array, rho_dot_i: Array, P_L: Array, a: Array, be: Array, r_L, nu_dot, nu_ddot, mu: float = MU_EARTH
) -> Array:
    """``rho_i''`` (``..., N, 3``) of eqs. 2.40-2.42, written out component by component:

        x_i'' = be_x + 2 nu' (y_i' - a_y) + nu'' d_y + nu'^2 d_x - mu (r_L + d_x)/R^3 + mu/r_L^2
        y_i'' = be_y - 2 nu' (x_i' - a_x) - nu'' d_x + nu'^2 d_y - mu d_y/R^3
        z_i'' = be_z - mu d_z/R^3,      d = rho_i - P^L,  R^3 = ((r_L + d_x)^2 + d_y^2 + d_z^2)^(3/2)

    with ``a``, ``be`` from :func:`constraint_terms`. The leader quantities get a trailing
    axis to broadcast over the points.
    """
    r_L, nu_dot, nu_ddot = (np.asarray(v, dtype=float)[..., None] for v in (r_L, nu_dot, nu_ddot))
    dx, dy, dz = np.moveaxis(rho_i - P_L, -1, 0)
    vx, vy, _ = np.moveaxis(rho_dot_i, -1, 0)
    ax, ay, _ = np.moveaxis(a, -1, 0)
    R3 = ((r_L + dx) ** 2 + dy * dy + dz * dz) ** 1.5
    gx = 2.0 * nu_dot * (vy - ay) + nu_ddot * dy + nu_dot**2 * dx - mu * (r_L + dx) / R3 + mu / r_L**2
    gy = -2.0 * nu_dot * (vx - ax) - nu_ddot * dx + nu_dot**2 * dy - mu * dy / R3
    gz = -mu * dz / R3
    return be + np.stack([gx, gy, gz], axis=-1)


def coupled_rhs(
    x: Array, r_L, nu_dot, nu_ddot, k: Array, mu: float = MU_EARTH, as_printed: bool = False
) -> Array:
    """``c'`` of the coupled model (module docstring), state ``(..., 13 + 9N)``.

    The c.m. and attitude blocks are :func:`simplified_rhs`; each point's acceleration is
    :func:`feature_acceleration` with its own position and velocity and ``w'`` of the
    attitude block.
    """
    x = np.asarray(x, dtype=float)
    N = n_points_coupled(x.shape[-1])
    xdot = np.zeros_like(x)
    s = x[..., : simplified_size(N)]
    xdot[..., : simplified_size(N)] = simplified_rhs(s, r_L, nu_dot, nu_ddot, k, mu)
    P_L = points_in_L(x, N)
    i0, i1 = simplified_size(N), simplified_size(N) + 3 * N
    rho_i = x[..., i0:i1].reshape(x.shape[:-1] + (N, 3))
    rho_dot_i = x[..., i1:].reshape(x.shape[:-1] + (N, 3))
    a, be = constraint_terms(x[..., OMEGA], xdot[..., OMEGA], P_L, as_printed)
    acc = feature_acceleration(rho_i, rho_dot_i, P_L, a, be, r_L, nu_dot, nu_ddot, mu)
    xdot[..., i0:i1] = x[..., i1:]
    xdot[..., i1:] = acc.reshape(x.shape[:-1] + (3 * N,))
    return xdot


def simplified_features(x: Array) -> Array:
    """Feature positions ``rho_i = rho_0 + D P_i`` (``..., N, 3``) of simplified states."""
    N = n_points_simplified(x.shape[-1])
    return x[..., None, RHO] + points_in_L(x, N)


def coupled_features(x: Array) -> Array:
    """Integrated feature positions ``rho_i`` (``..., N, 3``) of coupled states."""
    N = n_points_coupled(x.shape[-1])
    i0 = simplified_size(N)
    return x[..., i0 : i0 + 3 * N].reshape(x.shape[:-1] + (N, 3))


def coupled_initial(s: Array) -> Array:
    """Coupled state from a simplified one: ``rho_i = rho_0 + D P_i``, ``rho_i' = rho_0' + w x D P_i``."""
    s = np.asarray(s, dtype=float)
    N = n_points_simplified(s.shape[-1])
    P_L = points_in_L(s, N)
    rho_i = s[..., None, RHO] + P_L
    rho_dot_i = s[..., None, RHO_DOT] + np.cross(s[..., None, OMEGA], P_L)
    flat = s.shape[:-1] + (3 * N,)
    return np.concatenate([s, rho_i.reshape(flat), rho_dot_i.reshape(flat)], axis=-1)
