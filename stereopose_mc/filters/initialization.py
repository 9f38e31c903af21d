"""``initial_estimate: measurements``: the filters' start from the first stereo frame.

From the first frame (``t = 0``) of each trial (``core/initialization.py``):

- every visible feature's position and velocity in ``L`` by triangulation, with
  covariance ``C_i = (G^T R^-1 G)^-1`` (``R`` the filter's image and flow variances; the
  first filter's R is used for the shared start);
- ``rho = c``, the centroid of the visible points; the true centre of mass is
  ``c + g`` with ``g ~ N(0, sigma_c^2 I)`` (``centre_of_mass_sigma_m``): the common-mode
  term;
- ``rho_dot``, ``omega`` from the weighted rigid-body fit of the points' velocities
  (``rho_dot = v_c``, the centroid's velocity), weighted by the residuals' covariance with the
  lever arms' triangulation errors (``core.initialization.rigid_fit``);
- ``q``, ``k`` from their priors: the thesis's draw ``N(truth, P0)`` on those blocks (the
  same draw as ``truth_plus_noise``);
- ``P_i = D(q)^T (rho_i - c)``; a feature not visible at ``t = 0`` keeps the prior draw.

Covariance (first order; triangulation cross terms between different points neglected
against the common-mode term):

    P_rho = sigma_c^2 I + (1/N^2) sum C_pos,i           P_rho,P_i = -sigma_c^2 D
    P_rho_dot,P_i = -sigma_c^2 [omega x] D
    P_P_i,P_j = D^T (sigma_c^2 I + delta_ij C_pos,i) D + J_i P_qq J_j^T      P_q,P_i = P_qq J_i^T
    [rho_dot, omega] = fit covariance, plus [omega x] sigma_c^2 [omega x]^T on rho_dot
    P_rho_dot,rho = [omega x] sigma_c^2;   P_qq, P_kk from P0

with ``J_i = d (D(q)^T r_i) / d q``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..config.resolve import FilterSetup, Setup
from ..core import initialization as ini
from ..core import quaternion as qt
from ..core import state as st
from ..core.jacobians import dcm_derivative
from .relnav import channel_variances

Array = NDArray[np.float64]


def measurement_start(setup: Setup, fs: FilterSetup, y0: Array, visible0: Array, x_draw: Array) -> tuple[Array, Array]:
    """``(x0 (B, n), P0 (B, n, n))`` from the first frame ``y0 (B, N, C)``; ``x_draw`` gives q, k (and hidden points)."""
    B, n = x_draw.shape
    N = setup.n_points
    vis = np.flatnonzero(visible0)
    if vis.size < 3:
        raise ValueError("initial_estimate: measurements needs at least 3 features visible at t = 0")
    R8 = channel_variances(fs, False)[:8]
    rho_i, rho_dot_i = ini.triangulate(y0[:, vis], setup.baseline, setup.focal)
    C = ini.point_covariance(rho_i, rho_dot_i, setup.baseline, R8, setup.focal)
    c, v_c, w, cov_fit = ini.rigid_fit(rho_i, rho_dot_i, C)
    q = qt.normalize(x_draw[:, st.QUAT])
    D, dD = dcm_derivative(q)
    r = rho_i - c[:, None]
    pts = st.points(x_draw).copy()
    pts[:, vis] = np.einsum("bji,bnj->bni", D, r)  # D^T r_i
    x0 = st.assemble(c, v_c, w, q, pts, x_draw[:, st.k_slice(N)])

    s2 = setup.com_sigma**2
    P = np.zeros((B, n, n))
    P[:, st.RHO, st.RHO] = s2 * np.eye(3) + C[..., :3, :3].sum(1) / vis.size**2
    Wx = qt.skew(w)
    P[:, 3:9, 3:9] = cov_fit
    P[:, st.RHO_DOT, st.RHO_DOT] += s2 * Wx @ np.swapaxes(Wx, -1, -2)
    P[:, st.RHO_DOT, st.RHO] = s2 * Wx
    P[:, st.RHO, st.RHO_DOT] = s2 * np.swapaxes(Wx, -1, -2)
    P_qq = np.diag(setup.P0_diag[st.QUAT])
    P[:, st.QUAT, st.QUAT] = P_qq
    ks = st.k_slice(N)
    P[:, ks, ks] = np.diag(setup.P0_diag[ks])
    p0 = st.POINTS0
    # J_i = d(D^T r_i)/dq: column j is dD_j^T r_i
    J = np.einsum("bjkl,bnk->bnlj", dD, r)  # (B, N_vis, 3, 4)
    Dt = np.swapaxes(D, -1, -2)
    hidden = np.setdiff1d(np.arange(N), vis)
    for a, i in enumerate(vis):
        si = slice(p0 + 3 * i, p0 + 3 * i + 3)
        P[:, st.RHO, si] = -s2 * D
        P[:, si, st.RHO] = -s2 * Dt
        P[:, st.RHO_DOT, si] = -s2 * Wx @ D
        P[:, si, st.RHO_DOT] = np.swapaxes(P[:, st.RHO_DOT, si], -1, -2)
        P[:, st.QUAT, si] = P_qq @ np.swapaxes(J[:, a], -1, -2)
        P[:, si, st.QUAT] = J[:, a] @ P_qq
        for b_, j in enumerate(vis):
            sj = slice(p0 + 3 * j, p0 + 3 * j + 3)
            blk = s2 * np.eye(3) + (C[:, a, :3, :3] if a == b_ else 0.0)
            P[:, si, sj] = Dt @ blk @ D + J[:, a] @ P_qq @ np.swapaxes(J[:, b_], -1, -2)
    for i in hidden:
        si = slice(p0 + 3 * i, p0 + 3 * i + 3)
        P[:, si, si] = np.diag(setup.P0_diag[si])
    return x0, 0.5 * (P + np.swapaxes(P, -1, -2))
