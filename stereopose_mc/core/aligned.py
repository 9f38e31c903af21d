"""The aligned error state: coordinates in which the problem's near-symmetries are straight lines.

Two families of states give the same images at every instant (docs/filters.md, "The
aligned error state"):

- the **centre-of-mass gauge**: ``P_i + d`` for every point with ``rho - D d`` and
  ``rho_dot - omega x (D d)`` (broken only by the centre of mass's orbital dynamics);
- the **body-frame rotation**: ``q (x) dq`` with ``P_i -> R(dq)^T P_i`` (broken only by
  Euler's equations through the principal axes, which 100 s of a slow tumble barely see).

In the attitude chart of ``core.errorstate`` (``a`` in ``L``, additive points and centre
of mass) both are curves whose tangent depends on the estimate (``[P_i x]``, ``D``), so a
filter linearized at moving estimates gains information along them that no image holds:
the attitude becomes 2x overconfident in case B. The aligned error state

    e = [e_c (3), e_cdot (3), e_omega (3), delta (3), e_P1 ... e_PN (3N), e_k (2)]

with ``c = rho + D P_bar`` the centroid of the feature points in ``L`` (``P_bar`` their mean
in ``T``), ``c_dot = rho_dot + omega x (D P_bar)`` its velocity, ``delta`` a rotation of the
body frame (``q = q_ref (x) dq(delta)``, ``dq`` the chart of ``core.errorstate``) and the
points in the rotated body frame, ``P_i = R(delta)^T (P_i,ref + e_Pi)``:

    chart(x_ref, e):  q = q_ref (x) dq(delta),   P_i = R^T (P_i,ref + e_Pi),
                      omega = omega_ref + e_omega,   k = k_ref + e_k,
                      v = D_ref (P_bar,ref + mean e_P)   (= D P_bar),
                      rho = c_ref + e_c - v,   rho_dot = c_dot,ref + e_cdot - omega x v.

A pure ``delta`` is exactly the body-frame rotation and a common ``e_Pi = d`` (with
``e_c = e_cdot = 0``) exactly the gauge, at any reference and any size; every feature's
position ``c + D_ref (P_i,ref + e_Pi - P_bar,ref - mean e_P)`` and velocity in ``L``
depend neither on ``delta`` nor on the common part of ``e_P``. ``local`` is the exact
inverse of ``chart``; ``chart_jacobian`` and ``error_map`` are analytic (tests: finite
differences, ``T S = I``). Batched over leading axes; unit quaternions, SI units.
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import NDArray

from . import errorstate as es
from . import layout as lay
from . import quaternion as qt
from . import state as st
from .jacobians import dcm_derivative

Array = NDArray[np.float64]

E_C = slice(lay.E_RHO, lay.E_RHO + lay.VEC)  # the points' centroid in L
E_CDOT = slice(lay.E_RHO_DOT, lay.E_RHO_DOT + lay.VEC)  # its velocity
E_OMEGA = slice(lay.E_OMEGA, lay.E_OMEGA + lay.VEC)
DELTA = es.ATT  # the body-frame rotation block of the aligned error state (the attitude chart's a)


def left_matrix(p: Array) -> Array:
    """``L(p)`` (``...,4,4``) with ``p (x) r = L(p) r``."""
    p0, p1, p2, p3 = np.moveaxis(np.asarray(p, dtype=float), -1, 0)
    return np.stack(
        [
            np.stack([p0, -p1, -p2, -p3], -1),
            np.stack([p1, p0, -p3, p2], -1),
            np.stack([p2, p3, p0, -p1], -1),
            np.stack([p3, -p2, p1, p0], -1),
        ],
        axis=-2,
    )


def _points(x: Array) -> Array:
    """The feature points ``(..., N, 3)`` of states ``x``."""
    return st.points(x)


def centroid(x: Array) -> tuple[Array, Array, Array]:
    """``(c, c_dot, v)``: the points' centroid in ``L``, its velocity, and ``v = D P_bar``."""
    v = qt.matvec(qt.dcm(x[..., st.QUAT]), _points(x).mean(axis=-2))
    return x[..., st.RHO] + v, x[..., st.RHO_DOT] + qt.cross(x[..., st.OMEGA], v), v


def chart(x_ref: Array, e: Array) -> Array:
    """``x_ref [+] e`` in the aligned chart (module docstring)."""
    N = st.n_points(x_ref.shape[-1])
    shape = np.broadcast_shapes(x_ref.shape[:-1], e.shape[:-1])
    x_ref = np.broadcast_to(x_ref, shape + x_ref.shape[-1:])
    e = np.broadcast_to(e, shape + e.shape[-1:])
    x = np.empty(shape + (e.shape[-1] + 1,))
    c_ref, cd_ref, _ = centroid(x_ref)
    dq = es.small_quaternion(e[..., DELTA])
    x[..., st.QUAT] = qt.multiply(x_ref[..., st.QUAT], dq)
    u = _points(x_ref) + e[..., es.points_slice(N)].reshape(shape + (N, 3))
    x[..., st.points_slice(N)] = (u @ qt.dcm(dq)).reshape(shape + (3 * N,))  # rows u_i^T R = (R^T u_i)^T
    x[..., st.OMEGA] = x_ref[..., st.OMEGA] + e[..., E_OMEGA]
    x[..., st.k_slice(N)] = x_ref[..., st.k_slice(N)] + e[..., es.k_slice(N)]
    v = qt.matvec(qt.dcm(x_ref[..., st.QUAT]), u.mean(axis=-2))
    x[..., st.RHO] = c_ref + e[..., E_C] - v
    x[..., st.RHO_DOT] = cd_ref + e[..., E_CDOT] - qt.cross(x[..., st.OMEGA], v)
    return x


def local(x_ref: Array, x: Array) -> Array:
    """Inverse of ``chart``: ``e`` with ``x = x_ref [+] e``."""
    N = st.n_points(x.shape[-1])
    shape = np.broadcast_shapes(x_ref.shape[:-1], x.shape[:-1])
    x_ref = np.broadcast_to(x_ref, shape + x_ref.shape[-1:])
    x = np.broadcast_to(x, shape + x.shape[-1:])
    e = np.empty(shape + (x.shape[-1] - 1,))
    dq = qt.multiply(qt.conjugate(qt.normalize(x_ref[..., st.QUAT])), x[..., st.QUAT])
    dq = dq / np.linalg.norm(x[..., st.QUAT], axis=-1, keepdims=True)
    e[..., DELTA] = 2.0 * dq[..., 1:] / dq[..., :1]
    R = qt.dcm(dq)
    P = _points(x)
    e[..., es.points_slice(N)] = (P @ np.swapaxes(R, -1, -2) - _points(x_ref)).reshape(shape + (3 * N,))
    e[..., E_OMEGA] = x[..., st.OMEGA] - x_ref[..., st.OMEGA]
    e[..., es.k_slice(N)] = x[..., st.k_slice(N)] - x_ref[..., st.k_slice(N)]
    c_ref, cd_ref, _ = centroid(x_ref)
    c, cd, _ = centroid(x)
    e[..., E_C] = c - c_ref
    e[..., E_CDOT] = cd - cd_ref
    return e


def chart_jacobian(x_ref: Array, e: Array | None = None) -> Array:
    """``S = d (x_ref [+] e) / d e`` (``..., n, n-1``); at ``e = 0`` by default.

    ``dq/d delta = L(q_ref) d dq/d delta``; ``dP_i/de_Pi = R^T``,
    ``dP_i/d delta = [dR^T/d dq_j u_i]_j d dq/d delta``; ``d rho/d e_c = I``,
    ``d rho/d e_Pi = -D_ref / N``; ``d rho_dot/d e_cdot = I``, ``d rho_dot/d e_omega = [v x]``,
    ``d rho_dot/d e_Pi = -[omega x] D_ref / N``; identity on ``omega`` and ``k``.
    """
    n = x_ref.shape[-1]
    N = st.n_points(n)
    if e is None:
        e = np.zeros(x_ref.shape[:-1] + (n - 1,))
    shape = np.broadcast_shapes(x_ref.shape[:-1], e.shape[:-1])
    x_ref = np.broadcast_to(x_ref, shape + (n,))
    e = np.broadcast_to(e, shape + (n - 1,))
    S = np.zeros(shape + (n, n - 1))
    delta = e[..., DELTA]
    dq = es.small_quaternion(delta)
    Sq = es.small_quaternion_jacobian(delta)  # (..., 4, 3)
    S[..., st.QUAT, DELTA] = left_matrix(x_ref[..., st.QUAT]) @ Sq
    R, dR = dcm_derivative(dq)  # dR[..., j] = dR/d dq_j
    u = _points(x_ref) + e[..., es.points_slice(N)].reshape(shape + (N, 3))
    Rt = np.swapaxes(R, -1, -2)
    D_ref = qt.dcm(x_ref[..., st.QUAT])
    omega = x_ref[..., st.OMEGA] + e[..., E_OMEGA]
    v = qt.matvec(D_ref, u.mean(axis=-2))
    W = qt.skew(omega) @ D_ref / N
    for i in range(N):
        r, c = slice(lay.point(i), lay.point(i + 1)), slice(lay.e_point(i), lay.e_point(i + 1))
        S[..., r, c] = Rt
        # d (R^T u) / d dq_j = dR_j^T u: columns j of a 3 x 4 matrix
        dRtu = np.einsum("...jba,...b->...aj", dR, u[..., i, :])
        S[..., r, DELTA] = dRtu @ Sq
        S[..., st.RHO, c] = -D_ref / N
        S[..., st.RHO_DOT, c] = -W
    S[..., st.RHO, E_C] = np.eye(3)
    S[..., st.RHO_DOT, E_CDOT] = np.eye(3)
    S[..., st.RHO_DOT, E_OMEGA] = qt.skew(v)
    S[..., st.OMEGA, E_OMEGA] = np.eye(3)
    S[..., st.k_slice(N), es.k_slice(N)] = np.eye(lay.K_SIZE)
    return S


def error_map(x_ref: Array) -> Array:
    """``T = d e / d x`` at ``x_ref`` (``..., n-1, n``); ``T S = I`` and ``T q_ref = 0`` (no norm direction).

    ``d delta/dq = Xi_b = 2 [L(q_ref^*)]_vec``; ``d e_Pi/dP_i = I``, ``d e_Pi/dq = -[P_i x] Xi_b``;
    ``d e_c/d rho = I``, ``d e_c/dP_i = D/N``, ``d e_c/dq = [dD/dq_j P_bar]_j``;
    ``d e_cdot/d rho_dot = I``, ``d e_cdot/d omega = -[v x]``, ``d e_cdot/dP_i = [omega x] D/N``,
    ``d e_cdot/dq = [omega x] [dD/dq_j P_bar]_j``; identity on ``omega`` and ``k``.
    """
    n = x_ref.shape[-1]
    N = st.n_points(n)
    T = np.zeros(x_ref.shape[:-1] + (n - 1, n))
    qn = qt.normalize(x_ref[..., st.QUAT])
    Xi = 2.0 * left_matrix(qt.conjugate(qn))[..., 1:, :]
    D, dD = dcm_derivative(x_ref[..., st.QUAT])
    P = _points(x_ref)
    Pbar = P.mean(axis=-2)
    v = qt.matvec(D, Pbar)
    dv = np.einsum("...jab,...b->...aj", dD, Pbar)  # (..., 3, 4): d (D P_bar) / dq
    Om = qt.skew(x_ref[..., st.OMEGA])
    T[..., DELTA, st.QUAT] = Xi
    for i in range(N):
        r, c = slice(lay.e_point(i), lay.e_point(i + 1)), slice(lay.point(i), lay.point(i + 1))
        T[..., r, c] = np.eye(3)
        T[..., r, st.QUAT] = -qt.skew(P[..., i, :]) @ Xi
        T[..., E_C, c] = D / N
        T[..., E_CDOT, c] = Om @ D / N
    T[..., E_C, st.RHO] = np.eye(3)
    T[..., E_C, st.QUAT] = dv
    T[..., E_CDOT, st.RHO_DOT] = np.eye(3)
    T[..., E_CDOT, st.OMEGA] = -qt.skew(v)
    T[..., E_CDOT, st.QUAT] = Om @ dv
    T[..., E_OMEGA, st.OMEGA] = np.eye(3)
    T[..., es.k_slice(N), st.k_slice(N)] = np.eye(lay.K_SIZE)
    return T


def to_attitude_chart(x: Array, P: Array) -> Array:
    """The covariance ``P`` of the aligned error state at ``x`` in the attitude chart of ``core.errorstate``.

    ``M P M^T`` with ``M = T_attitude(x) S_aligned(x)`` (exact at first order: both are
    charts of the same state around the same point).
    """
    M = attitude_map(x)
    return M @ P @ np.swapaxes(M, -1, -2)


def attitude_map(x: Array) -> Array:
    """``M = T_attitude(x) S_aligned(x)``: the aligned error state at ``x`` to the attitude chart's, to first order."""
    return es.error_map(x) @ chart_jacobian(x)


def from_attitude_chart(x: Array, P: Array, M: Array | None = None) -> Array:
    """Inverse of ``to_attitude_chart``: ``M^-1 P M^-T`` (two solves, no inverse), symmetrized (``M``:
    ``attitude_map(x)`` when the caller has it)."""
    M = attitude_map(x) if M is None else M
    X = np.linalg.solve(M, P)
    Pa = np.swapaxes(np.linalg.solve(M, np.swapaxes(X, -1, -2)), -1, -2)
    return 0.5 * (Pa + np.swapaxes(Pa, -1, -2))


@functools.lru_cache(maxsize=16)
def gauge_complement(n: int) -> Array:
    """Orthonormal ``V (n-1, n-4)``: the complement of the gauge in the aligned error state.

    In this chart the centre-of-mass gauge is exactly the constant direction "the same
    ``e_Pi = d`` for every point" (``e_c``, ``e_cdot`` unchanged), whatever the reference and
    the size of ``d``: moving the truth along its gauge orbit adds ``R d`` (``R`` the small
    rotation between the two attitudes) to every ``e_Pi`` and nothing else.
    """
    N = st.n_points(n)
    G = np.zeros((n - 1, 3))
    G[es.points_slice(N)] = np.tile(np.eye(3), (N, 1)) / np.sqrt(N)
    Qf, _ = np.linalg.qr(G, mode="complete")
    V = Qf[:, 3:]
    V.flags.writeable = False  # (cached per n: shared by every caller)
    return V


def nees_report(x_hat: Array, P: Array, x_true: Array, M: Array | None = None) -> dict[str, Array]:
    """Full, gauge-projected and per-block NEES of the estimate ``(x_hat, P)`` (``P`` in the aligned chart).

    - ``nees``: ``e^T P^-1 e`` with ``e = local(x_hat, x_true)`` (``n - 1`` dof);
    - ``nees_gauge``: the same for ``V^T e`` with ``V^T P V`` (``gauge_complement``,
      ``n - 4`` dof): exactly invariant to where the estimate sits on its gauge orbit;
    - ``nees_<block>``: the blocks of the attitude-chart error state of
      ``core.errorstate`` (``rho, rho_dot, omega, attitude, feature_points, k``: the
      quantities a reader knows), its covariance ``M P M^T``, ``M = T_att S_aligned``.

    To first order these are the NEES of ``core.errorstate.nees_all``; unlike those, an
    error along the gauge or the body rotation does not leak, through their curvature in
    the attitude chart, into the directions the images measure to a fraction of a
    millimetre (docs/filters.md, Consistency).

    ``M``: ``attitude_map(x_hat)`` when the caller has it (else computed here).
    """
    x_true = np.broadcast_to(x_true, x_hat.shape)
    n = x_hat.shape[-1]
    e = local(x_hat, x_true)
    out = {"nees": es.mahalanobis2(e, P)}
    V = gauge_complement(n)
    # per-trial products (a stacked matvec, not one (B, n) x (n, n-4) GEMM: its rounding would depend on B)
    z = (np.swapaxes(V, 0, 1) @ e[..., None])[..., 0]
    out["nees_gauge"] = es.mahalanobis2(z, np.swapaxes(V, 0, 1) @ P @ V)
    eps = es.estimation_error(x_hat, x_true)
    M = attitude_map(x_hat) if M is None else M
    for name, b in es.error_blocks(st.n_points(n)).items():
        Mb = M[..., b, :]
        out[f"nees_{name}"] = es.mahalanobis2(eps[..., b], Mb @ P @ np.swapaxes(Mb, -1, -2))
    return out
