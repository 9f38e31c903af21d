"""Stereo camera measurement model (docs/model.md, thesis 3.1 and 6.1.3).

Right camera at the leader's centre of mass, left camera at ``+b`` along ``x``, both
looking along ``+y``, focal length 1 (normalized image coordinates). For a feature at
``rho_i = rho_0 + D P_i = [x, y, z]`` moving at ``rho_i' = rho_0' + w x (D P_i)``:

    u_R = x / y    v_R = z / y    u_L = (x - b) / y    v_L = z / y    d = u_L - u_R = -b / y

and the image velocities are the exact time derivatives of these. Per feature the
channels are ``[u_R, v_R, u_L, v_L, du_R, dv_R, du_L, dv_L]`` (+ ``d``). A feature with
``y <= 0`` is not visible.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import quaternion as qt
from . import state as st

Array = NDArray[np.float64]

CHANNELS = ("u_r", "v_r", "u_l", "v_l", "du_r", "dv_r", "du_l", "dv_l")
DISPARITY = "d"


def channels(disparity: bool) -> tuple[str, ...]:
    """Names of the per-feature measurement channels."""
    return CHANNELS + ((DISPARITY,) if disparity else ())


def feature_kinematics(x: Array) -> tuple[Array, Array]:
    """Positions and velocities ``(..., N, 3)`` of the feature points in ``L``."""
    D = qt.dcm(x[..., st.QUAT])
    r = st.points(x) @ np.swapaxes(D, -1, -2)
    rho_i = x[..., None, st.RHO] + r
    rho_dot_i = x[..., None, st.RHO_DOT] + qt.cross(x[..., None, st.OMEGA], r)
    return rho_i, rho_dot_i


def project(rho_i: Array, rho_dot_i: Array, baseline: float, disparity: bool = False, focal: float = 1.0) -> Array:
    """Image coordinates and velocities ``(..., N, 8|9)`` of points in ``L``.

    Every channel is linear in the focal length ``focal`` (1 = normalized coordinates).
    """
    x, y, z = np.moveaxis(rho_i, -1, 0)
    vx, vy, vz = np.moveaxis(rho_dot_i, -1, 0)
    iy = 1.0 / y
    xl = x - baseline
    u_r, v_r, u_l = x * iy, z * iy, xl * iy
    du_r = (vx * y - x * vy) * iy * iy
    dv_r = (vz * y - z * vy) * iy * iy
    du_l = (vx * y - xl * vy) * iy * iy
    cols = [u_r, v_r, u_l, v_r, du_r, dv_r, du_l, dv_r]
    if disparity:
        cols.append(u_l - u_r)
    out = np.stack(cols, axis=-1)
    return out if focal == 1.0 else focal * out


def h_features(x: Array, baseline: float, disparity: bool = False, focal: float = 1.0) -> Array:
    """Noise-free measurement of every feature, ``(..., N, 8|9)``."""
    rho_i, rho_dot_i = feature_kinematics(x)
    return project(rho_i, rho_dot_i, baseline, disparity, focal)


def visible(x: Array) -> Array:
    """Visibility ``(..., N)``: a feature is visible when its ``y > 0``."""
    rho_i, _ = feature_kinematics(x)
    return rho_i[..., 1] > 0.0


_FLOW = slice(4, 8)  # du_r, dv_r, du_l, dv_l among CHANNELS


def _mm3(A: Array, B: Array) -> Array:
    """``A @ B`` of ``(..., 3, 3)`` stacks as three elementwise products in a fixed order (a trial's bits do not
    depend on the batch it is in, as they may with ``matmul``)."""
    return A[..., :, 0, None] * B[..., None, 0, :] + A[..., :, 1, None] * B[..., None, 1, :] + (
        A[..., :, 2, None] * B[..., None, 2, :])  # fmt: skip


def flow_second_order_variance(x: Array, P_ww: Array, P_pp: Array, baseline: float, disparity: bool = False,
                               focal: float = 1.0) -> Array:  # fmt: skip
    """The variance ``(..., N, 8|9)`` the image-velocity rows' linearization leaves out (0 on the other channels).

    An image velocity ``f = (v_a p_y - p_a v_y) / p_y^2`` (``p``, ``v`` a feature's position and
    velocity in ``L``, ``v = rho_dot + w x r``, ``r = D P_i``; ``p_a`` is ``x`` or ``x - b`` or ``z``) is
    bilinear in the errors of ``w`` and of the feature point: ``v`` holds ``dw x dr``, and ``f``
    multiplies ``dv = dw x r`` by ``dp = dr``. That part is ``T = dw^T M dr`` with

        M = -[g x] + [r x] K              (rows: dw, columns: dr; [a x] b = a x b)

    ``g = df/dv``, ``K = d2f/dv dp``. For independent ``dw ~ N(0, P_ww)``, ``dP_i ~ N(0, P_pp[i])``
    (``S_r = D P_pp[i] D^T``) it has variance ``tr(M S_r M^T P_ww)``, added to the row's R (times
    ``focal^2``). It is large while both are uncertain (a prior of 1 deg/s and 1 m: ``1.7e-2`` m/s,
    against ``0.1 px/s`` of a 1000 px camera at 60 m, ``4e-3`` m/s) and vanishes as either converges.
    The cross-covariance of ``w`` and the points and the terms within one block are left out
    (tests/core/test_camera.py: within 5 % of sampled linearization errors).
    """
    D = qt.dcm(x[..., st.QUAT])[..., None, :, :]  # (..., 1, 3, 3)
    pts = st.points(x)
    r = pts[..., 0, None] * D[..., :, 0] + pts[..., 1, None] * D[..., :, 1] + pts[..., 2, None] * D[..., :, 2]
    rho_i = x[..., None, st.RHO] + r  # (elementwise, not feature_kinematics' matmul: the same bits in any batch)
    S_r = _mm3(_mm3(np.broadcast_to(D, P_pp.shape), P_pp), np.swapaxes(D, -1, -2))  # (..., N, 3, 3)
    Pw = P_ww[..., None, :, :]
    At = qt.skew(r)  # (-[r x])^T = [r x]
    px, y, pz = np.moveaxis(rho_i, -1, 0)
    iy = 1.0 / y
    out = np.zeros(rho_i.shape[:-1] + (len(channels(disparity)),))
    zero = np.zeros_like(y)
    for col, (a, pa) in zip((4, 5, 6), ((0, px), (2, pz), (0, px - baseline))):
        g = [zero, -pa * iy * iy, zero]
        g[a] = iy
        K = np.zeros(rho_i.shape[:-1] + (3, 3))  # d2f / dv dp
        K[..., a, 1] = K[..., 1, a] = -iy * iy
        K[..., 1, 1] = 2.0 * pa * iy**3
        M = _mm3(At, K) - qt.skew(np.stack(g, axis=-1))  # sum_m g_m eps_mkl = -[g x]_kl
        out[..., col] = (_mm3(_mm3(M, S_r), np.swapaxes(M, -1, -2)) * Pw).sum(axis=(-2, -1))
    out[..., 7] = out[..., 5]  # dv_l = dv_r
    return out if focal == 1.0 else focal**2 * out
