"""Analytic Jacobians of the process model and of the measurement models.

Every function takes states ``x (..., n)``, ``n = 13 + 3N + 2``, with any leading batch
axes, and keeps them. The leader's ``r_L, nu', nu''`` may be scalars or arrays that
broadcast to the batch shape.

Building blocks (docs/model.md; ``W = w + w_L``, ``w_T = D^T W``, ``I = diag(J)``,
``J = [e^k1, 1, e^-k2]``):

- ``D(q) = A(q) / |q|^2`` with ``A`` the homogeneous quadratic form, so
  ``dD/dq_j = (dA/dq_j - 2 q_j D) / |q|^2`` (``sum_j q_j dD/dq_j = 0``: D is scale-free);
- Euler's rate ``g(w_T) = -I^-1 (w_T x I w_T) = c * [w2 w3, w3 w1, w1 w2]`` with
  ``c = [(J2-J3)/J1, (J3-J1)/J2, (J1-J2)/J3]``, so ``G = dg/dw_T`` has rows
  ``[0, c1 w3, c1 w2]``, ``[c2 w3, 0, c2 w1]``, ``[c3 w2, c3 w1, 0]``, and ``dg/dk``
  follows from ``dJ1/dk1 = J1``, ``dJ3/dk2 = -J3``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import layout as lay
from . import quaternion as qt
from . import state as st
from .orbit import MU_EARTH

Array = NDArray[np.float64]

_N_SHARED = lay.COMMON  # columns rho, rho_dot, omega, q that every feature's rows touch


def _dA_dq_explicit(q: Array) -> Array:
    """``dA/dq_j`` (4,3,3) of the homogeneous DCM numerator ``A(q)`` at one ``q``."""
    q0, q1, q2, q3 = q
    return 2.0 * np.array(
        [
            [[q0, -q3, q2], [q3, q0, -q1], [-q2, q1, q0]],
            [[q1, q2, q3], [q2, -q1, -q0], [q3, q0, -q1]],
            [[-q2, q1, q0], [q1, q2, q3], [-q0, q3, -q2]],
            [[-q3, -q0, q1], [q0, -q3, q2], [q1, q2, q3]],
        ]
    )


# dA/dq_j is linear in q: dA/dq_j = sum_k _DA[k, j] q_k, stored as a (4, 36) matrix.
_DA = np.stack([_dA_dq_explicit(e) for e in np.eye(4)]).reshape(4, 36)

# q (x) [0, v] = M(v) q, with M(v) = sum_i v_i _M[i]; stored as (3, 16).
_M = np.array(
    [
        [[0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1], [0, 0, -1, 0]],
        [[0, 0, -1, 0], [0, 0, 0, -1], [1, 0, 0, 0], [0, 1, 0, 0]],
        [[0, 0, 0, -1], [0, 0, 1, 0], [0, -1, 0, 0], [1, 0, 0, 0]],
    ],
    dtype=float,
).reshape(3, 16)


def dcm_derivative(q: Array) -> tuple[Array, Array]:
    """``(D, dD)``: ``D(q)`` (``...,3,3``) and ``dD/dq_j`` (``...,4,3,3``, j first).

    ``dD/dq_j = (dA/dq_j - 2 q_j D) / |q|^2`` for ``D = A(q)/|q|^2`` (normalized DCM).
    """
    q = np.asarray(q, dtype=float)
    batch = q.shape[:-1]
    n2 = np.sum(q * q, axis=-1)[..., None, None]
    dA = (q @ _DA).reshape(batch + (4, 9))
    D = (0.5 / n2) * (q[..., None, :] @ dA)  # A = 1/2 sum_j q_j dA/dq_j (A is quadratic)
    dD = (dA - 2.0 * q[..., :, None] * D) / n2
    return D.reshape(batch + (3, 3)), dD.reshape(batch + (4, 3, 3))


def _leader(batch: tuple[int, ...], *values) -> list[Array]:
    """Leader quantities broadcast to the batch shape."""
    return [np.broadcast_to(np.asarray(v, dtype=float), batch) for v in values]


def _euler_terms(w_T: Array, k: Array) -> tuple[Array, Array, Array]:
    """``(g, G, dg/dk)`` of Euler's rate ``g = -I^-1 (w_T x I w_T)`` at ``w_T (...,3)``.

    ``g = c * p`` with ``p = [w2 w3, w3 w1, w1 w2]``; ``G = dg/dw_T`` (``...,3,3``);
    ``dg/dk = p * dc/dk`` (``...,3,2``).
    """
    J1 = np.exp(k[..., 0])
    J3 = np.exp(-k[..., 1])
    c = np.stack([(1.0 - J3) / J1, J3 - J1, (J1 - 1.0) / J3], axis=-1)
    dc_dk1 = np.stack([-(1.0 - J3) / J1, -J1, J1 / J3], axis=-1)
    dc_dk2 = np.stack([J3 / J1, -J3, (J1 - 1.0) / J3], axis=-1)
    w1, w2, w3 = np.moveaxis(w_T, -1, 0)
    p = np.stack([w2 * w3, w3 * w1, w1 * w2], axis=-1)
    G = np.zeros(w_T.shape[:-1] + (3, 3))
    G[..., 0, 1] = c[..., 0] * w3
    G[..., 0, 2] = c[..., 0] * w2
    G[..., 1, 0] = c[..., 1] * w3
    G[..., 1, 2] = c[..., 1] * w1
    G[..., 2, 0] = c[..., 2] * w2
    G[..., 2, 1] = c[..., 2] * w1
    dg_dk = np.stack([p * dc_dk1, p * dc_dk2], axis=-1)
    return c * p, G, dg_dk


def _T(a: Array) -> Array:
    """Transpose of the last two axes."""
    return np.swapaxes(a, -1, -2)


_cross = qt.cross


def _skew(v: Array) -> Array:
    """``[v x]`` (``...,3,3``)."""
    out = np.zeros(v.shape + (3,))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def _dDT_v(dD: Array, v: Array) -> Array:
    """``[dD/dq_j^T v]_j`` as columns (``...,3,4``)."""
    return _T((v[..., None, None, :] @ dD)[..., 0, :])


def _dD_v(dD: Array, v: Array) -> Array:
    """``[dD/dq_j v]_j`` as columns (``...,3,4``)."""
    return _T((dD @ v[..., None, :, None])[..., 0])


def gravity_gradient(rho: Array, r_L, mu: float = MU_EARTH) -> Array:
    """``d/d rho [-mu s / |s|^3] = -mu/|s|^3 (I - 3 s s^T/|s|^2)``, ``s = r_L e_x + rho``."""
    s = np.array(rho, dtype=float)
    s[..., 0] += r_L
    R2 = np.sum(s * s, axis=-1)[..., None, None]
    ss = s[..., :, None] * s[..., None, :]
    return -mu / (R2**1.5) * (np.eye(3) - 3.0 * ss / R2)


def F(x: Array, r_L, nu_dot, nu_ddot, mu: float = MU_EARTH) -> Array:
    """``df/dx`` (``...,n,n``) of ``dynamics.f``.

    Non-zero blocks (rows <- columns):

    - ``rho <- rho_dot``: ``I``;
    - ``rho_dot <- rho``: gravity gradient ``+ [[nu'^2, nu'', 0], [-nu'', nu'^2, 0], 0]``;
    - ``rho_dot <- rho_dot``: ``[[0, 2nu', 0], [-2nu', 0, 0], 0]``;
    - ``w <- w``: ``D G D^T - [w_L x]``;  ``w <- q_j``: ``dD_j g + D G dD_j^T W``;
      ``w <- k``: ``D dg/dk``;
    - ``q <- w``: ``1/2 Q(q) D^T``;  ``q <- q``: ``1/2 (M(D^T w) + Q(q) [dD_j^T w]_j)``
      with ``Q(q) v = M(v) q``.

    The rows of the feature points and of ``k`` are zero.
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[-1]
    N = st.n_points(n)
    batch = x.shape[:-1]
    rL, nd, ndd = _leader(batch, r_L, nu_dot, nu_ddot)
    out = np.zeros(batch + (n, n))

    # translation
    out[..., 0, 3] = out[..., 1, 4] = out[..., 2, 5] = 1.0
    A = gravity_gradient(x[..., st.RHO], rL, mu)
    nd2 = nd * nd
    A[..., 0, 0] += nd2
    A[..., 1, 1] += nd2
    A[..., 0, 1] += ndd
    A[..., 1, 0] -= ndd
    out[..., 3:6, 0:3] = A
    out[..., 3, 4] = 2.0 * nd
    out[..., 4, 3] = -2.0 * nd

    # rotation
    w = x[..., st.OMEGA]
    q = x[..., st.QUAT]
    ks = st.k_slice(N)
    D, dD = dcm_derivative(q)
    DT = _T(D)
    W = w.copy()
    W[..., 2] += nd
    w_T = (DT @ W[..., None])[..., 0]
    g, G, dg_dk = _euler_terms(w_T, x[..., ks])
    DG = D @ G
    dw_dw = DG @ DT
    dw_dw[..., 0, 1] += nd
    dw_dw[..., 1, 0] -= nd
    out[..., st.OMEGA, st.OMEGA] = dw_dw
    out[..., st.OMEGA, st.QUAT] = _dD_v(dD, g) + DG @ _dDT_v(dD, W)
    out[..., st.OMEGA, ks] = D @ dg_dk

    Q = qt.omega_matrix(q)
    v = (DT @ w[..., None])[..., 0]
    M = (v @ _M).reshape(batch + (4, 4))
    out[..., st.QUAT, st.OMEGA] = 0.5 * (Q @ DT)
    out[..., st.QUAT, st.QUAT] = 0.5 * (M + Q @ _dDT_v(dD, w))
    return out


def _projection_gradients(rho_i: Array, rho_dot_i: Array, baseline: float, disparity: bool) -> Array:
    """``[dh/d rho_i | dh/d rho_dot_i]`` (``...,N,C,6``) of ``camera.project`` (focal 1).

    ``u = x/y``: ``[1/y, -x/y^2, 0]``; ``du = vx/y - x vy/y^2``:
    ``d/d rho_i = [-vy/y^2, -vx/y^2 + 2 x vy/y^3, 0]``, ``d/d rho_dot_i = [1/y, -x/y^2, 0]``
    (likewise for ``z`` and ``x - b``); ``d = -b/y``: ``[0, b/y^2, 0]``.
    """
    x, y, z = np.moveaxis(rho_i, -1, 0)
    vx, vy, vz = np.moveaxis(rho_dot_i, -1, 0)
    iy = 1.0 / y
    iy2 = iy * iy
    xl = x - baseline
    # built channel-first (contiguous writes), returned as a (..., N, C, 6) view
    out = np.zeros((lay.n_channels(disparity), 6) + y.shape)
    # positions: u_R, v_R, u_L, v_L (= v_R)
    out[0, 0] = out[2, 0] = iy
    out[0, 1] = -x * iy2
    out[2, 1] = -xl * iy2
    out[1, 1] = out[3, 1] = -z * iy2
    out[1, 2] = out[3, 2] = iy
    # velocities: du_R, dv_R, du_L, dv_L (= dv_R); d/d rho_dot_i repeats the position rows
    out[4:8, 3:6] = out[0:4, 0:3]
    vyy = 2.0 * vy * iy2 * iy
    vy2 = -vy * iy2
    out[4, 0] = out[6, 0] = vy2
    out[4, 1] = -vx * iy2 + x * vyy
    out[6, 1] = -vx * iy2 + xl * vyy
    out[5, 1] = out[7, 1] = -vz * iy2 + z * vyy
    out[5, 2] = out[7, 2] = vy2
    if disparity:
        out[8, 1] = baseline * iy2
    return np.moveaxis(out, (0, 1), (-2, -1))


def H_features_compact(
    x: Array, baseline: float, disparity: bool = False, focal: float = 1.0
) -> tuple[Array, Array]:
    """Jacobian of ``camera.h_features`` in compact form ``(shared, own)``.

    ``shared (..., N, C, 13)``: columns ``[rho, rho_dot, omega, q]``;
    ``own (..., N, C, 3)``: columns of feature ``i``'s own point ``P_i``. With
    ``r_i = D P_i``, ``rho_i = rho + r_i``, ``rho_dot_i = rho_dot + w x r_i`` and the
    projection gradients ``Jp = dh/d rho_i``, ``Jv = dh/d rho_dot_i``:

        d/d rho = Jp,  d/d rho_dot = Jv,  d/d w = -Jv [r_i x],
        d/d q_j = Jp dD_j P_i + Jv [w x] dD_j P_i,   d/d P_i = (Jp + Jv [w x]) D,

    i.e. ``[shared | own] = [Jp | Jv] K_i`` with the (6, 16) chain matrix
    ``K_i = [[I, 0, 0, dr_i/dq, D], [0, I, -[r_i x], [w x] dr_i/dq, [w x] D]]``.
    """
    x = np.asarray(x, dtype=float)
    batch = x.shape[:-1]
    P = st.points(x)
    N = P.shape[-2]
    w = x[..., st.OMEGA]
    D, dD = dcm_derivative(x[..., st.QUAT])
    r = P @ _T(D)  # (...,N,3)
    rho_i = x[..., None, st.RHO] + r
    rho_dot_i = x[..., None, st.RHO_DOT] + _cross(w[..., None, :], r)
    Jpv = _projection_gradients(rho_i, rho_dot_i, baseline, disparity)

    K = np.zeros(batch + (N, 6, _N_SHARED + 3))
    eye = np.eye(3)
    rho, rho_dot, omega = (slice(o, o + 3) for o in (lay.RHO, lay.RHO_DOT, lay.OMEGA))
    q, qp = slice(lay.QUAT, lay.QUAT + lay.QUAT_SIZE), slice(lay.QUAT, _N_SHARED + 3)  # q, and q with the point
    K[..., 0:3, rho] = eye
    K[..., 3:6, rho_dot] = eye
    K[..., 3:6, omega] = -_skew(r)
    # dr_i/dq_j = dD_j P_i: (...,4,3,3)(...,3,N) -> (...,4,3,N) -> (...,N,3,4)
    dr_dq = np.swapaxes((dD.reshape(batch + (12, 3)) @ _T(P)).reshape(batch + (4, 3, N)), -3, -1)
    K[..., 0:3, q] = dr_dq
    K[..., 0:3, _N_SHARED : _N_SHARED + 3] = D[..., None, :, :]
    K[..., 3:6, qp] = _skew(w)[..., None, :, :] @ K[..., 0:3, qp]
    out = Jpv @ K
    if focal != 1.0:
        out *= focal
    return out[..., :_N_SHARED], out[..., _N_SHARED:]


def dense_features(shared: Array, own: Array, n: int) -> Array:
    """Dense ``(..., N, C, n)`` feature Jacobian from its compact form."""
    N, C = shared.shape[-3], shared.shape[-2]
    out = np.zeros(shared.shape[:-3] + (N, C, n))
    out[..., :_N_SHARED] = shared
    for i in range(N):
        c0 = st.POINTS0 + 3 * i
        out[..., i, :, c0 : c0 + 3] = own[..., i, :, :]
    return out


def H_features(x: Array, baseline: float, disparity: bool = False, focal: float = 1.0) -> Array:
    """Jacobian ``(..., N, C, n)`` of ``camera.h_features`` (C = 8, or 9 with disparity).

    Feature ``i``'s rows are non-zero only in the columns of ``rho, rho_dot, omega, q``
    and of its own point ``P_i`` (see ``H_features_compact``).
    """
    x = np.asarray(x, dtype=float)
    shared, own = H_features_compact(x, baseline, disparity, focal)
    return dense_features(shared, own, x.shape[-1])


def H_pseudo(x: Array, alpha: Array, nu_dot, nu_ddot) -> Array:
    """Jacobian ``(..., 3, n)`` of ``inertia.h_pseudo`` w.r.t. the state (alpha given).

    ``h = D^T a - g(w_T)``, ``a = alpha + w_L x w + w_L'``, ``w_T = D^T W``:

        dh/dw = D^T [w_L x] - G D^T,   dh/dq_j = dD_j^T a - G dD_j^T W,   dh/dk = -dg/dk.
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[-1]
    N = st.n_points(n)
    batch = x.shape[:-1]
    nd, ndd = _leader(batch, nu_dot, nu_ddot)
    w = x[..., st.OMEGA]
    ks = st.k_slice(N)
    D, dD = dcm_derivative(x[..., st.QUAT])
    DT = _T(D)
    a = np.array(np.broadcast_to(alpha, batch + (3,)), dtype=float)
    a[..., 0] -= nd * w[..., 1]
    a[..., 1] += nd * w[..., 0]
    a[..., 2] += ndd
    W = w.copy()
    W[..., 2] += nd
    w_T = (DT @ W[..., None])[..., 0]
    _, G, dg_dk = _euler_terms(w_T, x[..., ks])
    out = np.zeros(batch + (3, n))
    GDT = G @ DT
    dh_dw = -GDT
    # D^T [w_L x] = nd * [D^T e_y, -D^T e_x, 0] as columns
    dh_dw[..., :, 0] += nd[..., None] * DT[..., :, 1]
    dh_dw[..., :, 1] -= nd[..., None] * DT[..., :, 0]
    out[..., st.OMEGA] = dh_dw
    out[..., st.QUAT] = _dDT_v(dD, a) - G @ _dDT_v(dD, W)
    out[..., ks] = -dg_dk
    return out
