"""The relative state vector (13 + 3N + 2): named blocks and conversions (offsets in ``core.layout``).

``x = [rho_0 (3), rho_dot_0 (3), omega (3), q (4), P_1 ... P_N (3N), k1, k2]``

- ``rho_0``, ``rho_dot_0``: target centre of mass relative to the leader, in ``L`` (m, m/s);
- ``omega``: angular velocity of ``T`` relative to ``L``, components in ``L`` (rad/s);
- ``q``: scalar-first quaternion, ``v^L = D(q) v^T``;
- ``P_i``: feature points in ``T`` (m);
- ``k1 = ln(Ix/Iy)``, ``k2 = ln(Iy/Iz)``, so ``I_T = diag(e^k1, 1, e^-k2)``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import layout as lay

Array = NDArray[np.float64]

RHO = slice(lay.RHO, lay.RHO + lay.VEC)
RHO_DOT = slice(lay.RHO_DOT, lay.RHO_DOT + lay.VEC)
OMEGA = slice(lay.OMEGA, lay.OMEGA + lay.VEC)
QUAT = slice(lay.QUAT, lay.QUAT + lay.QUAT_SIZE)
POINTS0 = lay.POINTS
size = lay.n_state  # length of the state for ``n_points`` feature points
n_points = lay.n_points  # number of feature points of a state of length ``n``


def points_slice(n_points: int) -> slice:
    return slice(POINTS0, POINTS0 + lay.VEC * n_points)


def k_slice(n_points: int) -> slice:
    s = POINTS0 + lay.VEC * n_points
    return slice(s, s + lay.K_SIZE)


def points(x: Array) -> Array:
    """Feature points ``(..., N, 3)`` of states ``x (..., n)``."""
    N = n_points(x.shape[-1])
    return x[..., points_slice(N)].reshape(x.shape[:-1] + (N, lay.VEC))


def inertia_diag(k: Array) -> Array:
    """Principal moments ``(..., 3) = [e^k1, 1, e^-k2]`` from ``k (..., 2)``."""
    k = np.asarray(k, dtype=float)
    return np.stack([np.exp(k[..., 0]), np.ones(k.shape[:-1]), np.exp(-k[..., 1])], axis=-1)


def k_from_inertia(inertia: Array) -> Array:
    """``[ln(Ix/Iy), ln(Iy/Iz)]`` from principal moments ``(..., 3)``."""
    inertia = np.asarray(inertia, dtype=float)
    return np.stack(
        [np.log(inertia[..., 0] / inertia[..., 1]), np.log(inertia[..., 1] / inertia[..., 2])], axis=-1
    )


def assemble(rho, rho_dot, omega, q, pts, k) -> Array:
    """Concatenate the blocks (each with the same leading axes) into a state."""
    pts = np.asarray(pts, dtype=float)
    flat = pts.reshape(pts.shape[:-2] + (pts.shape[-2] * 3,))
    return np.concatenate(
        [np.asarray(a, dtype=float) for a in (rho, rho_dot, omega, q)] + [flat, np.asarray(k, dtype=float)],
        axis=-1,
    )


def block_index(n_points: int) -> dict[str, slice]:
    """Named blocks of the state, for Q and P0 assembly and reports."""
    return dict(zip(lay.NAMES, (RHO, RHO_DOT, OMEGA, QUAT, points_slice(n_points), k_slice(n_points))))
