"""Inertia ratios: the pseudo-measurement of Euler's equation (thesis 6.2.2).

Given a measured relative angular acceleration ``alpha`` (in ``L``), Euler's equation
for the torque-free target must hold:

    0 = D^T (alpha + w_L' + w_L x w) + I^-1 (w_T x I w_T),    w_T = D^T (w + w_L)

``h_pseudo`` returns the right-hand side (3 rows); its observed value is zero. The
noise on ``alpha`` enters through the rotation ``D^T``, so its covariance is
``sigma_alpha^2 I_3`` whatever the attitude.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import quaternion as qt
from . import state as st
from .dynamics import omega_leader

Array = NDArray[np.float64]


def h_pseudo(x: Array, alpha: Array, nu_dot, nu_ddot) -> Array:
    """Euler residual ``(..., 3)`` of state ``x`` for measured acceleration ``alpha``."""
    N = st.n_points(x.shape[-1])
    omega = x[..., st.OMEGA]
    D = qt.dcm(x[..., st.QUAT])
    wL = omega_leader(nu_dot, omega.shape[:-1])
    a = alpha + qt.cross(wL, omega)
    a[..., 2] += nu_ddot
    w_T = qt.rmatvec(D, omega + wL)
    inertia = st.inertia_diag(x[..., st.k_slice(N)])
    gyro = qt.cross(w_T, inertia * w_T) / inertia
    return qt.rmatvec(D, a) + gyro
