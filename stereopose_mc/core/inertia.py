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


def euler_coefficients(k: Array) -> tuple[Array, Array, Array]:
    """``c (..., 3)`` with ``I^-1 (w x I w) = c * [w2 w3, w3 w1, w1 w2]``, ``dc/dk (..., 3, 2)``, ``d2c/dk2 (..., 3, 2, 2)``.

    For ``I = [e^k1, 1, e^-k2]`` (``state.inertia_diag``): ``c1 = (I3 - I2)/I1 = e^(-k1-k2) - e^-k1``,
    ``c2 = (I1 - I3)/I2 = e^k1 - e^-k2``, ``c3 = (I2 - I1)/I3 = e^k2 - e^(k1+k2)``; the derivatives follow.
    """
    I1, I2, I3 = np.moveaxis(st.inertia_diag(k), -1, 0)
    c = np.stack([(I3 - I2) / I1, (I1 - I3) / I2, (I2 - I1) / I3], axis=-1)
    r13, r31 = I3 / I1, I1 / I3
    dc = np.stack([np.stack([-c[..., 0], -r13], -1), np.stack([I1, I3], -1), np.stack([-r31, c[..., 2]], -1)], -2)
    ddc = np.stack(
        [
            np.stack([np.stack([c[..., 0], r13], -1), np.stack([r13, r13], -1)], -2),
            np.stack([np.stack([I1, 0 * I1], -1), np.stack([0 * I1, -I3], -1)], -2),
            np.stack([np.stack([-r31, -r31], -1), np.stack([-r31, c[..., 2]], -1)], -2),
        ],
        -3,
    )
    return c, dc, ddc


# Small products by elementwise sums, not matmul/einsum: a trial's bits do not depend on the batch it is in
def _mm(A: Array, B: Array) -> Array:
    return (A[..., :, :, None] * B[..., None, :, :]).sum(axis=-2)


def _vm(v: Array, A: Array) -> Array:
    return (v[..., :, None] * A).sum(axis=-2)


def _dot(a: Array, b: Array) -> Array:
    return (a * b).sum(axis=-1)


# the pair (a, b) of body rates multiplying row i of the gyroscopic term: w_a w_b
_PAIRS = ((1, 2), (2, 0), (0, 1))


def pseudo_second_order_variance(x: Array, P_ww: Array, P_kk: Array, P_kw: Array, nu_dot) -> Array:
    """The variance ``(..., 3)`` the pseudo rows' linearization leaves out, per row (in ``T``).

    Row ``i`` of ``h_pseudo`` has the gyroscopic term ``g_i = c_i(k) w_a w_b`` with
    ``w_T = D^T (w + w_L)``: quadratic in ``w`` and a product with ``k``. For Gaussian errors
    ``dw ~ N(0, P_ww)``, ``dk ~ N(0, P_kk)`` (cross-covariance ``P_kw``) around the estimate, the
    part of ``g_i`` beyond the Jacobian is ``c dw_a dw_b + dc dm + dc dw_a dw_b + (m0/2) dk^T c'' dk``
    with ``S = D^T P_ww D`` the body-rate covariance, ``dm = (w_b e_a + w_a e_b) . dw_T`` the linear
    part of ``m = w_a w_b`` (``m0`` its value), ``dc = c_i' . dk``. Its variance by Isserlis' theorem:

        (c^2 + s_c^2) (S_aa S_bb + S_ab^2) + s_c^2 s_m^2 + cov(dc, dm)^2
          + 2 c (Cov(dw_a, dc) Cov(dw_b, dm) + Cov(dw_a, dm) Cov(dw_b, dc)) + m0^2/2 tr((c'' P_kk)^2)

    exact for the part quadratic in ``w``; the ``dc dw_a dw_b`` term is taken as if ``dk`` and ``dw``
    were independent and higher orders of ``c(k)`` are left out, so with ``k`` uncertain by 0.2
    and strongly correlated with ``w`` it is low by up to 1.5x (tests/core/test_inertia.py).
    Attitude errors are left out (``D^T`` is linear in them to first order). Adding this to the
    pseudo rows' ``R`` is the second-order EKF's correction; it matters while ``w`` is uncertain
    (``P_ww`` of ``(1 deg/s)^2`` gives ``~3e-4 rad/s^2`` against a ``sigma_alpha`` of ``1e-6``)
    and vanishes as ``w`` converges.
    """
    omega = x[..., st.OMEGA]
    D = qt.dcm(x[..., st.QUAT])
    w_T = qt.rmatvec(D, omega + omega_leader(nu_dot, omega.shape[:-1]))
    S = _mm(_mm(np.swapaxes(D, -1, -2), P_ww), D)
    C_kw = _mm(P_kw, D)  # Cov(dk, dw_T) (..., 2, 3)
    c, dc, ddc = euler_coefficients(x[..., st.k_slice(st.n_points(x.shape[-1]))])
    out = np.empty(omega.shape)
    for i, (a, b) in enumerate(_PAIRS):
        gm = np.zeros(omega.shape)
        gm[..., a] = w_T[..., b]
        gm[..., b] = w_T[..., a]
        g = dc[..., i, :]
        u = _vm(g, C_kw)  # Cov(dc, dw_T)
        Sg = _vm(gm, S)  # Cov(dw_T, dm) (S symmetric)
        s_m2 = _dot(Sg, gm)
        s_c2 = _dot(_vm(g, P_kk), g)
        cov = _dot(u, gm)
        m0 = w_T[..., a] * w_T[..., b]
        A = _mm(ddc[..., i, :, :], P_kk)  # the part quadratic in dk: (m0 / 2) dk^T c'' dk, variance m0^2/2 tr(A A)
        kk = 0.5 * m0**2 * (A * np.swapaxes(A, -1, -2)).sum(axis=(-2, -1))
        # Cov(c dw_a dw_b, dc dm) = c (Cov(dw_a, dc) Cov(dw_b, dm) + Cov(dw_a, dm) Cov(dw_b, dc)) (Isserlis)
        mixed = 2.0 * c[..., i] * (u[..., a] * Sg[..., b] + Sg[..., a] * u[..., b])
        quad = S[..., a, a] * S[..., b, b] + S[..., a, b] ** 2
        out[..., i] = (c[..., i] ** 2 + s_c2) * quad + s_c2 * s_m2 + cov**2 + kk + mixed
    return out


def rate_second_order_variance(x: Array, P_ww: Array, P_kk: Array, P_kw: Array, nu_dot) -> Array:
    """A bound ``(..., 3)`` on the variance, per axis of ``L``, that the rate's dynamics' linearization leaves out.

    The filter's ``omega' = D w_T' - w_L' - w_L x omega`` (docs/model.md) holds Euler's gyroscopic term
    ``w_T' = -I^-1 (w_T x I w_T)``, the pseudo rows' own (``h_pseudo``): beyond the Jacobian, its remainder under
    errors ``dw ~ N(0, P_ww)``, ``dk ~ N(0, P_kk)`` is the pseudo rows' remainder ``r`` (in ``T``, of variance
    ``v_b``: ``pseudo_second_order_variance``) rotated into ``L``: ``D r``. Its cross-row covariances are not
    formed, so each axis takes the Cauchy-Schwarz bound ``Var((D r)_a) <= (sum_b |D_ab| sqrt(v_b))^2``, which holds
    whatever they are (at most 3 x the axis's variance, when all three rows are equal and fully correlated).
    Over a step ``dt`` the prediction's ``omega`` moves by ``dt`` times that remainder: ``dt^2`` times the bound is
    the process noise the second-order EKF adds to ``omega`` (``filters.relnav.process_noise``).
    """
    v = pseudo_second_order_variance(x, P_ww, P_kk, P_kw, nu_dot)
    D = qt.dcm(x[..., st.QUAT])
    s = np.sqrt(np.maximum(v, 0.0))  # (a variance: negative only by round-off of its terms)
    a = np.abs(D)
    return ((a[..., 0] * s[..., :1] + a[..., 1] * s[..., 1:2]) + a[..., 2] * s[..., 2:]) ** 2
