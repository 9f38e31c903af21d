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
