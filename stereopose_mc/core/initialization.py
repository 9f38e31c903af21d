"""A start from the first stereo frame: triangulation and a rigid-body fit of image velocities.

Camera geometry of docs/model.md (right camera at the origin, left at ``+b`` along ``x``, both
looking along ``+y``, focal length ``f``). For one feature with measurements
``[u_R, v_R, u_L, v_L, du_R, dv_R, du_L, dv_L]``, with ``v = (v_R + v_L)/2`` and
``dv = (dv_R + dv_L)/2`` (the two cameras see the same ``v``):

    y  = f b / (u_R - u_L),   x = u_R y / f,   z = v y / f
    vy = -(du_R - du_L) y^2 / (f b)
    vx = (du_R y^2 / f + x vy) / y,   vz = (dv y^2 / f + z vy) / y

(exact inverses of the projection and its time derivative; the least-squares solution of
the 8 channels for the 6 unknowns). Their covariance is ``(G^T R^-1 G)^-1`` with ``G`` the
analytic Jacobian of the projection at the triangulated point.

Rigid-body fit: every point's velocity is ``rho_dot_i = v_c + omega x r_i`` with
``r_i = rho_i - c`` about the centroid ``c`` of the points; weighted least squares with
``A_i = [I, -[r_i x]]`` and weights ``W_i``:

    [v_c; omega] = (sum A_i^T W_i A_i)^-1 sum A_i^T W_i rho_dot_i,  covariance (sum A_i^T W_i A_i)^-1

The lever arms ``r_i`` are triangulated too: a depth error ``d rho_i`` moves the residual by
``-omega x d rho_i``, as much as the velocity's own error where stereo depth is poor (a short
baseline at long range). So ``W_i`` is the inverse of the residual's covariance
``G_i C_i G_i^T``, ``G_i = [-[omega x], I]`` on ``[rho_i, rho_dot_i]`` (errors in the variables,
"effective variance"), with ``omega`` from the previous fit: the first fit weights by the
velocity covariance alone, ``FIT_ITERATIONS`` refits follow (the weights depend on ``omega``
only through that product, so the fixed point is reached in two or three).

Batched over leading axes; solves, never inverses.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import quaternion as qt
from .jacobians import _projection_gradients

Array = NDArray[np.float64]


def triangulate(y: Array, baseline: float, focal: float = 1.0) -> tuple[Array, Array]:
    """Positions and velocities in ``L`` (``..., N, 3`` each) from ``y (..., N, >= 8)``."""
    u_r, v_r, u_l, v_l, du_r, dv_r, du_l, dv_l = np.moveaxis(y[..., :8] / focal, -1, 0)
    v, dv = 0.5 * (v_r + v_l), 0.5 * (dv_r + dv_l)
    Y = baseline / (u_r - u_l)
    X, Z = u_r * Y, v * Y
    vy = -(du_r - du_l) * Y * Y / baseline
    vx = (du_r * Y * Y + X * vy) / Y
    vz = (dv * Y * Y + Z * vy) / Y
    return np.stack([X, Y, Z], -1), np.stack([vx, vy, vz], -1)


def point_covariance(rho_i: Array, rho_dot_i: Array, baseline: float, R_diag: Array, focal: float = 1.0) -> Array:
    """``(G^T R^-1 G)^-1`` (``..., N, 6, 6``) of ``[rho_i, rho_dot_i]`` from the 8 channels (``R_diag (8,)``)."""
    G = focal * _projection_gradients(rho_i, rho_dot_i, baseline, False)  # (..., N, 8, 6)
    info = np.swapaxes(G, -1, -2) @ (G / R_diag[:, None])
    return np.linalg.solve(info, np.broadcast_to(np.eye(6), info.shape))


FIT_ITERATIONS = 3  # refits with the errors-in-variables weights (module docstring)


def rigid_fit(rho_i: Array, rho_dot_i: Array, C: Array, iterations: int = FIT_ITERATIONS
              ) -> tuple[Array, Array, Array, Array]:  # fmt: skip
    """``(c, v_c, omega, cov)``: centroid, its velocity, the rate and ``cov (..., 6, 6)`` of ``[v_c, omega]``.

    ``C (..., N, 6, 6)``: each point's covariance of ``[rho_i, rho_dot_i]`` (``point_covariance``); the fit's
    weights are the residuals' (module docstring), refitted ``iterations`` times after a first fit on the
    velocities' covariance alone (``iterations = 0``: that fit, the lever arms taken as exact).
    """
    c = rho_i.mean(axis=-2)
    r = rho_i - c[..., None, :]
    A = np.concatenate([np.broadcast_to(np.eye(3), r.shape + (3,)), -qt.skew(r)], axis=-1)  # (..., N, 3, 6)
    S = C[..., 3:, 3:]  # the residuals' covariance, first without the lever arms' errors
    for it in range(iterations + 1):
        WA = np.linalg.solve(S, A)  # W_i A_i
        N = np.einsum("...nji,...njk->...ik", A, WA)
        rhs = np.einsum("...nji,...nj->...i", WA, rho_dot_i)
        theta = np.linalg.solve(N, rhs[..., None])[..., 0]
        if it < iterations:  # G_i C_i G_i^T with G_i = [-[omega x], I]
            Wx = qt.skew(theta[..., None, 3:])  # (..., 1, 3, 3)
            G = np.concatenate([-np.broadcast_to(Wx, r.shape + (3,)), np.broadcast_to(np.eye(3), r.shape + (3,))],
                               axis=-1)  # fmt: skip
            S = G @ C @ np.swapaxes(G, -1, -2)
    cov = np.linalg.solve(N, np.broadcast_to(np.eye(6), N.shape))
    return c, theta[..., :3], theta[..., 3:], 0.5 * (cov + np.swapaxes(cov, -1, -2))
