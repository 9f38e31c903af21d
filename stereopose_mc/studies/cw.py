"""Clohessy-Wiltshire (Hill) relative motion: linear ODE, closed form and transition matrix.

Thesis section 2.3, in the leader's LVLH frame ``L`` (x radial, y along-track, z normal)
with the reference orbit's mean motion ``n = sqrt(mu / a^3)`` and no forcing:

    x'' - 2 n y' - 3 n^2 x = 0
    y'' + 2 n x'           = 0          (thesis eqs. 2.29-2.31)
    z'' + n^2 z            = 0

For the state ``s = [x, y, z, x', y', z']`` these are ``s' = A s`` and ``s(t) = Phi(t) s(0)``
with (``c = cos nt``, ``S = sin nt``)

    x(t)  = (4 - 3c) x0 + S/n x0' + 2(1 - c)/n y0'
    y(t)  = 6(S - nt) x0 + y0 - 2(1 - c)/n x0' + (4S - 3nt)/n y0'
    z(t)  = c z0 + S/n z0'
    x'(t) = 3nS x0 + c x0' + 2S y0'
    y'(t) = -6n(1 - c) x0 - 2S x0' + (4c - 3) y0'
    z'(t) = -nS z0 + c z0'

which is the thesis's eqs. 2.33, 2.35 and 2.36 with the impulses set to zero. (The
thesis's Laplace form, eq. 2.34, prints ``- 2 n x0`` in the second right-hand entry;
``+ 2 n x0`` is what its own time-domain solution 2.36 needs.) The equations are the
linearization of the nonlinear model of docs/model.md about ``rho = 0`` on a circular orbit.
Every function takes leading batch axes (``...``) and keeps them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def cw_matrix(n: float) -> Array:
    """System matrix ``A`` (6, 6) of ``s' = A s`` for the CW equations at mean motion ``n``."""
    A = np.zeros((6, 6))
    A[0:3, 3:6] = np.eye(3)
    A[3, 0] = 3.0 * n * n
    A[3, 4] = 2.0 * n
    A[4, 3] = -2.0 * n
    A[5, 2] = -n * n
    return A


def cw_stm(n: float, t: ArrayLike) -> Array:
    """State-transition matrix ``Phi(t)`` (``t.shape + (6, 6)``) of the CW equations (module docstring)."""
    t = np.asarray(t, dtype=float)
    nt = n * t
    c, S = np.cos(nt), np.sin(nt)
    Phi = np.zeros(t.shape + (6, 6))
    Phi[..., 0, 0] = 4.0 - 3.0 * c
    Phi[..., 0, 3] = S / n
    Phi[..., 0, 4] = 2.0 * (1.0 - c) / n
    Phi[..., 1, 0] = 6.0 * (S - nt)
    Phi[..., 1, 1] = 1.0
    Phi[..., 1, 3] = -2.0 * (1.0 - c) / n
    Phi[..., 1, 4] = (4.0 * S - 3.0 * nt) / n
    Phi[..., 2, 2] = c
    Phi[..., 2, 5] = S / n
    Phi[..., 3, 0] = 3.0 * n * S
    Phi[..., 3, 3] = c
    Phi[..., 3, 4] = 2.0 * S
    Phi[..., 4, 0] = -6.0 * n * (1.0 - c)
    Phi[..., 4, 3] = -2.0 * S
    Phi[..., 4, 4] = 4.0 * c - 3.0
    Phi[..., 5, 2] = -n * S
    Phi[..., 5, 5] = c
    return Phi


def cw_propagate(s0: ArrayLike, n: float, t: ArrayLike) -> Array:
    """States ``s(t) = Phi(t) s0``: ``s0 (..., 6)``, ``t (T,)`` -> ``(..., T, 6)``."""
    s0 = np.asarray(s0, dtype=float)
    Phi = cw_stm(n, np.atleast_1d(np.asarray(t, dtype=float)))
    return np.einsum("tij,...j->...ti", Phi, s0)


def cw_intercept_velocity(rho0: ArrayLike, n: float, t_f: float) -> Array:
    """Initial velocity ``v0 (..., 3)`` that brings the CW position from ``rho0`` to 0 at ``t_f``.

    Solves ``Phi_rv(t_f) v0 = -Phi_rr(t_f) rho0`` (the position rows of ``Phi``); ``Phi_rv``
    is singular only at isolated times (e.g. ``n t_f = pi`` for the z block).
    """
    rho0 = np.asarray(rho0, dtype=float)
    Phi = cw_stm(n, t_f)
    rhs = -np.einsum("ij,...j->...i", Phi[:3, :3], rho0)
    return np.linalg.solve(Phi[:3, 3:], rhs[..., None])[..., 0]
