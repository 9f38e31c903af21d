"""The error state of the relative-navigation problem: multiplicative attitude, gauge, NEES.

The filter state ``x (n = 13 + 3N + 2)`` carries a unit quaternion; its error lives in a
space of dimension ``n_e = n - 1 = 12 + 3N + 2``:

    eps = [d rho (3), d rho_dot (3), d omega (3), a (3), d P_1 ... d P_N (3N), d k (2)]

with the attitude error ``a`` the rotation vector, in ``L``, of the rotation that takes the
reference attitude to the other one: ``q = dq(a) (x) q_ref``, ``a ~ 2 vec(q (x) q_ref^-1)``.

- ``chart(x_ref, eps)`` (the "boxplus"): ``x = x_ref + eps`` on every block but the
  attitude, ``q = normalize([1, a/2]) (x) q_ref`` there (a Gibbs-type chart, smooth,
  exact inverse ``local``); ``chart_jacobian`` is its analytic Jacobian ``dx/deps``;
- ``attitude_map(q_ref)``: ``Xi = 2 [vec rows of (. (x) q_ref^-1)]`` (3 x 4), so that
  ``a = Xi (q - q_ref)`` to first order; ``error_map(x_ref)`` is ``T = d eps / d x``
  (``n_e x n``) and ``T S = I`` with ``S = chart_jacobian(x_ref, 0)``;
- the centre-of-mass gauge: shifting every ``P_i`` by ``d`` (in ``T``) and ``rho`` by
  ``-D d``, ``rho_dot`` by ``-omega x (D d)`` leaves every feature's position and velocity
  in ``L``, hence every image measurement, unchanged; ``gauge_basis`` spans these 3
  directions in ``eps`` coordinates;
- NEES of the full error state (``n_e`` dof), of each block, and gauge-projected
  (``n_e - 3`` dof): ``z = V^T eps``, ``z^T (V^T P V)^-1 z`` with ``V`` an orthonormal basis
  of the orthogonal complement of the gauge directions.

Every function is batched over leading axes (trial axis first) and returns new arrays.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import quaternion as qt
from . import layout as lay
from . import state as st

Array = NDArray[np.float64]

ATT = slice(lay.E_ROT, lay.E_ROT + lay.VEC)  # attitude block of the error state
HEAD = slice(0, lay.QUAT)  # rho, rho_dot, omega: the same offsets in the state and the error state
BLOCKS = ("rho", "rho_dot", "omega", "attitude", "feature_points", "k")
GAUGE_DOF = 3
BLOCK_PROBE_N = 16  # any valid state length (one feature point): the NEES names do not depend on N


def error_size(n: int) -> int:
    """Dimension ``n - 1`` of the error state of a state of length ``n``."""
    return n - 1


def error_blocks(n_points: int) -> dict[str, slice]:
    """Named blocks of the error state."""
    return {
        "rho": slice(lay.E_RHO, lay.E_RHO + lay.VEC),
        "rho_dot": slice(lay.E_RHO_DOT, lay.E_RHO_DOT + lay.VEC),
        "omega": slice(lay.E_OMEGA, lay.E_OMEGA + lay.VEC),
        "attitude": ATT,
        "feature_points": points_slice(n_points),
        "k": k_slice(n_points),
    }


def points_slice(n_points: int) -> slice:
    """The feature points' block of the error state (either chart)."""
    return slice(lay.E_POINTS, lay.e_point(n_points))


def k_slice(n_points: int) -> slice:
    """``e_k``'s block of the error state (either chart)."""
    return slice(lay.e_point(n_points), lay.n_error(n_points))


def nees_dof(n: int) -> dict[str, int]:
    """Chi-square degrees of freedom of each NEES of a state of length ``n``."""
    N = st.n_points(n)
    d = {"nees": error_size(n), "nees_gauge": error_size(n) - GAUGE_DOF}
    for name, s in error_blocks(N).items():
        d[f"nees_{name}"] = s.stop - s.start
    return d


def right_matrix(r: Array) -> Array:
    """``R(r)`` (``...,4,4``) with ``p (x) r = R(r) p``."""
    r0, r1, r2, r3 = np.moveaxis(np.asarray(r, dtype=float), -1, 0)
    return np.stack(
        [
            np.stack([r0, -r1, -r2, -r3], -1),
            np.stack([r1, r0, r3, -r2], -1),
            np.stack([r2, -r3, r0, r1], -1),
            np.stack([r3, r2, -r1, r0], -1),
        ],
        axis=-2,
    )


def attitude_map(q_ref: Array) -> Array:
    """``Xi (...,3,4) = 2 [R(q_ref^*)]_{1:4,:}``: ``a = 2 vec((q - q_ref) (x) q_ref^*)`` to first order."""
    return 2.0 * right_matrix(qt.conjugate(qt.normalize(q_ref)))[..., 1:, :]


def small_quaternion(a: Array) -> Array:
    """``dq(a) = [1, a/2] / |[1, a/2]|`` (``...,4``)."""
    u = np.concatenate([np.ones(a.shape[:-1] + (1,)), 0.5 * a], axis=-1)
    return u / np.linalg.norm(u, axis=-1, keepdims=True)


def small_quaternion_jacobian(a: Array) -> Array:
    """``d dq / d a`` (``...,4,3``) of ``small_quaternion``: ``(I - p p^T) / |u| [0; I/2]``."""
    u = np.concatenate([np.ones(a.shape[:-1] + (1,)), 0.5 * a], axis=-1)
    s = np.linalg.norm(u, axis=-1)[..., None, None]
    p = u / s[..., 0]
    du = np.zeros(a.shape[:-1] + (4, 3))
    du[..., 1:, :] = 0.5 * np.eye(3)
    return (du - p[..., :, None] * (p[..., None, :] @ du)) / s


def _split(x: Array) -> tuple[Array, Array]:
    return np.concatenate([x[..., HEAD], x[..., lay.POINTS :]], axis=-1), x[..., st.QUAT]


def chart(x_ref: Array, eps: Array) -> Array:
    """``x_ref [+] eps``: additive on every block, ``q = dq(a) (x) q_ref`` on the attitude."""
    x = np.empty(eps.shape[:-1] + (eps.shape[-1] + 1,))
    x[..., HEAD] = x_ref[..., HEAD] + eps[..., HEAD]
    x[..., lay.POINTS :] = x_ref[..., lay.POINTS :] + eps[..., lay.E_POINTS :]
    x[..., st.QUAT] = qt.multiply(small_quaternion(eps[..., ATT]), x_ref[..., st.QUAT])
    return x


def local(x_ref: Array, x: Array) -> Array:
    """Inverse of ``chart``: ``eps`` with ``x = x_ref [+] eps`` (``a = 2 vec(dq) / dq_0``)."""
    eps = np.empty(x.shape[:-1] + (x.shape[-1] - 1,))
    eps[..., HEAD] = x[..., HEAD] - x_ref[..., HEAD]
    eps[..., lay.E_POINTS :] = x[..., lay.POINTS :] - x_ref[..., lay.POINTS :]
    dq = qt.multiply(x[..., st.QUAT], qt.conjugate(qt.normalize(x_ref[..., st.QUAT])))
    dq = dq / np.linalg.norm(x[..., st.QUAT], axis=-1, keepdims=True)
    eps[..., ATT] = 2.0 * dq[..., 1:] / dq[..., :1]
    return eps


def chart_jacobian(x_ref: Array, eps: Array | None = None) -> Array:
    """``S = d (x_ref [+] eps) / d eps`` (``..., n, n-1``); at ``eps = 0`` by default."""
    n = x_ref.shape[-1]
    if eps is None:
        eps = np.zeros(x_ref.shape[:-1] + (n - 1,))
    S = np.zeros(eps.shape[:-1] + (n, n - 1))
    S[..., HEAD, HEAD] = np.eye(lay.QUAT)
    S[..., lay.POINTS :, lay.E_POINTS :] = np.eye(n - lay.POINTS)
    S[..., st.QUAT, ATT] = right_matrix(x_ref[..., st.QUAT]) @ small_quaternion_jacobian(eps[..., ATT])
    return S


def error_map(x_ref: Array) -> Array:
    """``T = d eps / d x`` at ``x_ref`` (``..., n-1, n``): identity blocks and ``Xi(q_ref)``."""
    n = x_ref.shape[-1]
    T = np.zeros(x_ref.shape[:-1] + (n - 1, n))
    T[..., HEAD, HEAD] = np.eye(lay.QUAT)
    T[..., lay.E_POINTS :, lay.POINTS :] = np.eye(n - lay.POINTS)
    T[..., ATT, st.QUAT] = attitude_map(x_ref[..., st.QUAT])
    return T


def to_error_covariance(x_ref: Array, P: Array) -> Array:
    """``T P T^T``: a covariance of the full state in error-state coordinates at ``x_ref``."""
    T = error_map(x_ref)
    return T @ P @ np.swapaxes(T, -1, -2)


def estimation_error(x_hat: Array, x_true: Array) -> Array:
    """``eps`` of the estimate relative to the truth: ``x_hat = x_true [+] eps`` (``..., n-1``)."""
    return local(np.broadcast_to(x_true, x_hat.shape), x_hat)


def gauge_basis(x: Array) -> Array:
    """The 3 centre-of-mass gauge directions (``..., n-1, 3``) in ``eps`` coordinates at ``x``.

    Column ``j``: ``d rho = -D e_j``, ``d rho_dot = -omega x (D e_j)``, ``d P_i = e_j`` for
    every ``i``; every other block 0.
    """
    n = x.shape[-1]
    N = st.n_points(n)
    D = qt.dcm(x[..., st.QUAT])
    G = np.zeros(x.shape[:-1] + (n - 1, 3))
    G[..., st.RHO, :] = -D
    G[..., st.RHO_DOT, :] = -(qt.skew(x[..., st.OMEGA]) @ D)
    p = error_blocks(N)["feature_points"]
    G[..., p, :] = np.tile(np.eye(3), (N, 1))
    return G


def gauge_act(x: Array, d: Array) -> Array:
    """The exact gauge move of ``x`` by ``d (..., 3)`` (in ``T``): a new state, same images.

    ``P_i + d`` for every point, ``rho - D d``, ``rho_dot - omega x (D d)``; ``omega``, ``q``,
    ``k`` unchanged. Every feature's position ``rho + D P_i`` and velocity
    ``rho_dot + omega x (D P_i)`` in ``L`` is unchanged exactly, for any ``d``.
    """
    x = np.array(x, dtype=float, copy=True)
    d = np.broadcast_to(d, x.shape[:-1] + (3,))
    v = qt.matvec(qt.dcm(x[..., st.QUAT]), d)
    x[..., st.RHO] -= v
    x[..., st.RHO_DOT] -= qt.cross(x[..., st.OMEGA], v)
    N = st.n_points(x.shape[-1])
    for i in range(N):
        x[..., lay.point(i) : lay.point(i + 1)] += d
    return x


def gauge_act_jacobian(x: Array, d: Array) -> Array:
    """``J = d local(g(x), g(x [+] e)) / d e`` at ``e = 0`` (``..., n-1, n-1``), ``g = gauge_act(., d)``.

    With ``v = D(q) d``: the identity but for ``d rho' / d a = [v x]``,
    ``d rho_dot' / d omega = [v x]`` and ``d rho_dot' / d a = [omega x][v x]`` (the attitude
    chart turns ``D`` into ``(I + [a x]) D``, so ``v`` into ``v + a x v``).
    """
    ne = x.shape[-1] - 1
    v = qt.matvec(qt.dcm(x[..., st.QUAT]), np.broadcast_to(d, x.shape[:-1] + (3,)))
    Vx = qt.skew(v)
    J = np.broadcast_to(np.eye(ne), x.shape[:-1] + (ne, ne)).copy()
    J[..., st.RHO, ATT] = Vx
    J[..., st.RHO_DOT, st.OMEGA] = Vx
    J[..., st.RHO_DOT, ATT] = qt.skew(x[..., st.OMEGA]) @ Vx
    return J


def gauge_complement(x: Array) -> Array:
    """Orthonormal basis ``V (..., n-1, n-4)`` of the complement of ``gauge_basis(x)``."""
    G = gauge_basis(x)
    Qf, _ = np.linalg.qr(G, mode="complete")
    return Qf[..., :, GAUGE_DOF:]


def _nees(e: Array, P: Array) -> Array:
    """``e^T P^-1 e`` by Cholesky, NaN where ``P`` is not positive definite."""
    out = np.full(e.shape[:-1], np.nan)
    ok = np.isfinite(e).all(-1) & np.isfinite(P).all((-1, -2))
    if not ok.any():
        return out
    try:
        L = np.linalg.cholesky(P[ok])
        w = np.linalg.solve(L, e[ok][..., None])[..., 0]
        out[ok] = np.sum(w * w, axis=-1)
    except np.linalg.LinAlgError:
        for i in np.flatnonzero(ok):
            try:
                w = np.linalg.solve(np.linalg.cholesky(P[i]), e[i])
                out[i] = w @ w
            except np.linalg.LinAlgError:
                pass
    return out


def mahalanobis2(e: Array, P: Array) -> Array:
    """``e^T P^-1 e`` (``...``) by Cholesky; NaN where ``P`` is not positive definite or ``e`` not finite."""
    return _nees(e, P)


def nees_all(eps: Array, P_eps: Array, x_ref: Array) -> dict[str, Array]:
    """Full, per-block and gauge-projected NEES (``...``) of errors ``eps`` with covariance ``P_eps``.

    Keys as ``nees_dof``: ``nees`` (``n-1`` dof), ``nees_<block>``, ``nees_gauge`` (``n-4``).
    """
    n = eps.shape[-1] + 1
    out = {"nees": _nees(eps, P_eps)}
    for name, s in error_blocks(st.n_points(n)).items():
        out[f"nees_{name}"] = _nees(eps[..., s], P_eps[..., s, s])
    out["nees_gauge"] = _nees_projected(eps, P_eps, x_ref)
    return out


def _nees_projected(eps: Array, P_eps: Array, x_ref: Array) -> Array:
    V = gauge_complement(x_ref)
    z = (np.swapaxes(V, -1, -2) @ eps[..., None])[..., 0]
    return _nees(z, np.swapaxes(V, -1, -2) @ P_eps @ V)
