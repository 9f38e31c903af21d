"""Local nonlinear observability: the Hermann-Krener rank test (thesis ch. 4).

Two layers:

1. **Generic linear algebra** (:func:`rank_analysis`): the numerical rank, the singular
   values and an orthonormal basis of the null space (the locally unobservable
   directions) of any observability-type matrix ``O`` (rows: gradients of observed
   functions, columns: state components). Columns are scaled by a typical magnitude of
   each state component and rows are equilibrated before the SVD, so the rank decision
   does not depend on the units the state happens to be written in. The same function
   serves any other observability matrix, e.g. an observability Gramian built from a
   filter's ``F`` and ``H`` along a trajectory.

2. **The torque-free rigid body of thesis ch. 4** (state ``x = [w_x, w_y, w_z, I_x, I_y,
   I_z]`` in principal axes, output ``y = h(x) = w``):

       f(x) = [I^-1 (-w x I w); 0; 0; 0],   i.e.  w_i' = c_i w_j w_k,  c_i = (I_j - I_k) / I_i

   for the cyclic triples ``(i, j, k) = (x, y, z), (y, z, x), (z, x, y)`` (thesis eqs.
   4.9-4.13). The Lie derivatives of ``h`` along ``f`` are, component by component,

       L^0 h_i = w_i
       L^1 h_i = c_i w_j w_k
       L^2 h_i = sum_m (d L^1 h_i / d w_m) f_m = c_i w_i (c_j w_k^2 + c_k w_j^2)

   and the observability matrix is ``O = [dL^0 h; dL^1 h (; dL^2 h)]`` with gradients
   taken analytically here (``dc_i/dI_i = -c_i/I_i``, ``dc_i/dI_j = 1/I_i``,
   ``dc_i/dI_k = -1/I_i``). For generic ``w`` and ``I`` its rank is 5 and its null space
   is spanned by ``[0, 0, 0, I_x, I_y, I_z]``: only the inertia ratios are observable.

3. **The full filter state** (last section): the discrete observability Gramian
   ``W = sum_k Phi(t_k,t_0)^T H_k^T R_k^-1 H_k Phi(t_k,t_0)`` from given one-step
   transitions and measurement Jacobians (:func:`observability_gramian`), its eigen-analysis
   in scaled coordinates with chosen directions projected out (:func:`gramian_eigen`), the
   directions that are invisible to ``h`` by construction (the quaternion norm, the
   body-frame gauge, the centre-of-mass shift), and the CRLB ``(W + P0^-1)^-1``. The
   scenario plumbing is in ``stereopose_mc/studies/observability.py``.

All kernels take any leading batch axes ``(...)``; :func:`rank_analysis`,
:func:`gramian_eigen` and :func:`crlb_covariance` work on one matrix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .quaternion import dcm, omega_matrix
from .state import POINTS0, QUAT
from .state import n_points as n_points_of

Array = NDArray[np.float64]

STATE_NAMES: tuple[str, ...] = ("w_x", "w_y", "w_z", "I_x", "I_y", "I_z")
"""Names of the components of the Euler observability state ``[w, I]``."""

_CYCLIC = ((0, 1, 2), (1, 2, 0), (2, 0, 1))
DEFAULT_RTOL = 1e-9
"""Default relative threshold on the scaled singular values (``s / s_max > rtol`` counts)."""


# --------------------------------------------------------------------------- generic


@dataclass(frozen=True)
class RankAnalysis:
    """Result of :func:`rank_analysis`.

    ``singular_values``: of ``O`` as given (descending, in the units of ``O``);
    ``scaled_singular_values``: of the scaled, equilibrated matrix, divided by its largest
    (descending; the rank counts those above ``rtol``); ``null_space``: ``(n, n - rank)``
    orthonormal columns in the original state coordinates, each with a fixed sign.
    """

    rank: int
    singular_values: Array
    scaled_singular_values: Array
    null_space: Array
    rtol: float


def _fix_sign(v: Array, preferred: int = 0, tol: float = 1e-8) -> Array:
    """``v`` or ``-v``: the one with a positive component ``preferred`` if that component
    is not negligible (``|v_p| > tol |v|``), else with its largest-magnitude component positive."""
    p = preferred if abs(v[preferred]) > tol * np.linalg.norm(v) else int(np.argmax(np.abs(v)))
    return -v if v[p] < 0 else v


def rank_analysis(
    O: Array,
    column_scale: Array | None = None,
    rtol: float = DEFAULT_RTOL,
    sign_component: int = 0,
) -> RankAnalysis:
    """Numerical rank and null space of one observability matrix ``O`` (m x n).

    With ``D = diag(column_scale)`` (a typical magnitude of each state component, so the
    scaled state ``x' = D^-1 x`` is O(1)) and ``W = diag(1 / |row_r(O D)|)`` (zero rows
    left alone), the SVD of ``O' = W O D`` decides the rank: ``rank = #{s'_i > rtol s'_1}``.
    ``W`` and ``D`` are nonsingular, so ``rank(O') = rank(O)``, and a null vector ``n'``
    of ``O'`` maps to the null vector ``n = D n'`` of ``O``; the basis is re-orthonormalized
    (QR) and each column's sign fixed (component ``sign_component`` positive when it is
    not negligible).
    """
    O = np.asarray(O, dtype=float)
    if O.ndim != 2:
        raise ValueError(f"rank_analysis takes one matrix (m, n), got shape {O.shape}")
    n = O.shape[1]
    d = np.ones(n) if column_scale is None else np.asarray(column_scale, dtype=float)
    if d.shape != (n,) or np.any(~np.isfinite(d)) or np.any(d <= 0):
        raise ValueError(f"column_scale must be {n} positive finite numbers, got {d}")
    if not np.all(np.isfinite(O)):
        raise ValueError("observability matrix has non-finite entries")
    raw = np.linalg.svd(O, compute_uv=False)
    Od = O * d
    norms = np.linalg.norm(Od, axis=1)
    Os = Od / np.where(norms > 0, norms, 1.0)[:, None]
    # full_matrices so that V has n rows even when m < n
    _, s, vt = np.linalg.svd(Os, full_matrices=True)
    s_rel = s / s[0] if s.size and s[0] > 0 else np.zeros_like(s)
    rank = int(np.sum(s_rel > rtol))
    null_scaled = vt[rank:].T  # (n, n - rank)
    if null_scaled.shape[1]:
        basis, _ = np.linalg.qr(d[:, None] * null_scaled)
        basis = np.stack([_fix_sign(basis[:, i], sign_component) for i in range(basis.shape[1])], axis=1)
    else:
        basis = np.zeros((n, 0))
    return RankAnalysis(rank=rank, singular_values=raw, scaled_singular_values=s_rel, null_space=basis, rtol=rtol)


# --------------------------------------------------------------------------- Euler (ch. 4)


def _split(x: Array) -> tuple[Array, Array]:
    x = np.asarray(x, dtype=float)
    if x.shape[-1] != 6:
        raise ValueError(f"Euler observability state has 6 components [w, I], got shape {x.shape}")
    return x[..., :3], x[..., 3:]


def euler_coefficients(inertia: Array) -> Array:
    """``c_i = (I_j - I_k) / I_i`` for cyclic ``(i, j, k)``; shape ``(..., 3)``."""
    inertia = np.asarray(inertia, dtype=float)
    return np.stack([(inertia[..., j] - inertia[..., k]) / inertia[..., i] for i, j, k in _CYCLIC], axis=-1)


def euler_coefficient_gradient(inertia: Array) -> Array:
    """``dc_i / dI_m`` ``(..., 3, 3)``: ``-c_i/I_i`` (m = i), ``1/I_i`` (m = j), ``-1/I_i`` (m = k)."""
    inertia = np.asarray(inertia, dtype=float)
    c = euler_coefficients(inertia)
    g = np.zeros(inertia.shape[:-1] + (3, 3))
    for i, j, k in _CYCLIC:
        g[..., i, i] = -c[..., i] / inertia[..., i]
        g[..., i, j] = 1.0 / inertia[..., i]
        g[..., i, k] = -1.0 / inertia[..., i]
    return g


def euler_f(x: Array) -> Array:
    """Drift ``f(x) = [I^-1 (-w x I w); 0, 0, 0]`` ``(..., 6)`` (torque-free Euler, principal axes)."""
    w, inertia = _split(x)
    wdot = -np.cross(w, inertia * w) / inertia
    return np.concatenate([wdot, np.zeros_like(inertia)], axis=-1)


def lie_derivatives(x: Array, order: int = 1) -> Array:
    """``[L^0 h, ..., L^order h]`` stacked ``(..., 3 (order + 1))`` for ``h = w`` (order <= 2).

    ``L^0 h_i = w_i``, ``L^1 h_i = c_i w_j w_k``, ``L^2 h_i = c_i w_i (c_j w_k^2 + c_k w_j^2)``.
    """
    _check_order(order)
    w, inertia = _split(x)
    c = euler_coefficients(inertia)
    out = [w]
    if order >= 1:
        out.append(np.stack([c[..., i] * w[..., j] * w[..., k] for i, j, k in _CYCLIC], axis=-1))
    if order >= 2:
        out.append(
            np.stack(
                [
                    c[..., i] * w[..., i] * (c[..., j] * w[..., k] ** 2 + c[..., k] * w[..., j] ** 2)
                    for i, j, k in _CYCLIC
                ],
                axis=-1,
            )
        )
    return np.concatenate(out, axis=-1)


def _check_order(order: int) -> None:
    if order not in (1, 2):
        raise ValueError(f"Lie derivative order must be 1 or 2, got {order}")


def grad_L0h(x: Array) -> Array:
    """``d L^0 h / dx = [I_3, 0]`` ``(..., 3, 6)``."""
    w, _ = _split(x)
    g = np.zeros(w.shape[:-1] + (3, 6))
    g[..., [0, 1, 2], [0, 1, 2]] = 1.0
    return g


def grad_L1h(x: Array) -> Array:
    """``d L^1 h / dx`` ``(..., 3, 6)`` of ``L^1 h_i = c_i w_j w_k``.

    ``d/dw_j = c_i w_k``, ``d/dw_k = c_i w_j``, ``d/dw_i = 0``, ``d/dI_m = (dc_i/dI_m) w_j w_k``.
    E.g. ``d L^1 h_x / d I_x = -(I_y - I_z) w_y w_z / I_x^2`` (thesis eq. 4.13, first row).
    """
    w, inertia = _split(x)
    c = euler_coefficients(inertia)
    dc = euler_coefficient_gradient(inertia)
    g = np.zeros(w.shape[:-1] + (3, 6))
    for i, j, k in _CYCLIC:
        g[..., i, j] = c[..., i] * w[..., k]
        g[..., i, k] = c[..., i] * w[..., j]
        g[..., i, 3:] = dc[..., i, :] * (w[..., j] * w[..., k])[..., None]
    return g


def grad_L2h(x: Array) -> Array:
    """``d L^2 h / dx`` ``(..., 3, 6)`` of ``L^2 h_i = c_i w_i (c_j w_k^2 + c_k w_j^2)``.

    ``d/dw_i = c_i (c_j w_k^2 + c_k w_j^2)``, ``d/dw_j = 2 c_i c_k w_i w_j``,
    ``d/dw_k = 2 c_i c_j w_i w_k``, ``d/dI_m = w_i [dc_i/dI_m (c_j w_k^2 + c_k w_j^2)
    + c_i (dc_j/dI_m w_k^2 + dc_k/dI_m w_j^2)]``.
    """
    w, inertia = _split(x)
    c = euler_coefficients(inertia)
    dc = euler_coefficient_gradient(inertia)
    g = np.zeros(w.shape[:-1] + (3, 6))
    for i, j, k in _CYCLIC:
        bracket = c[..., j] * w[..., k] ** 2 + c[..., k] * w[..., j] ** 2
        g[..., i, i] = c[..., i] * bracket
        g[..., i, j] = 2.0 * c[..., i] * c[..., k] * w[..., i] * w[..., j]
        g[..., i, k] = 2.0 * c[..., i] * c[..., j] * w[..., i] * w[..., k]
        dbracket = dc[..., j, :] * (w[..., k] ** 2)[..., None] + dc[..., k, :] * (w[..., j] ** 2)[..., None]
        g[..., i, 3:] = w[..., i, None] * (dc[..., i, :] * bracket[..., None] + c[..., i, None] * dbracket)
    return g


def observability_matrix(x: Array, order: int = 1) -> Array:
    """Hermann-Krener matrix ``O = [dL^0 h; dL^1 h (; dL^2 h)]`` ``(..., 3 (order + 1), 6)`` (thesis eq. 4.15)."""
    _check_order(order)
    blocks = [grad_L0h(x), grad_L1h(x)]
    if order >= 2:
        blocks.append(grad_L2h(x))
    return np.concatenate(blocks, axis=-2)


def euler_scale(x: Array) -> Array:
    """Typical magnitudes ``(6,)`` of ``[w, I]`` for :func:`rank_analysis`: ``|w|`` (1 rad/s if
    ``w = 0``) for the rates and ``max I`` for the moments (a change of time and mass units)."""
    w, inertia = _split(x)
    wn = float(np.linalg.norm(w))
    return np.array([wn if wn > 0 else 1.0] * 3 + [float(np.max(np.abs(inertia)))] * 3)


def euler_rank_test(omega: Array, inertia: Array, order: int = 1, rtol: float = DEFAULT_RTOL) -> RankAnalysis:
    """The ch. 4 test at one state: rank and null space of ``O`` at ``x = [omega, inertia]``.

    ``omega`` in rad/s (principal axes), ``inertia`` the principal moments in kg m^2 (> 0).
    The null-space sign makes the ``I_x`` component positive when it is not negligible.
    """
    omega = np.asarray(omega, dtype=float)
    inertia = np.asarray(inertia, dtype=float)
    if omega.shape != (3,) or inertia.shape != (3,):
        raise ValueError("omega and inertia must each have 3 components")
    if np.any(~np.isfinite(omega)) or np.any(~np.isfinite(inertia)) or np.any(inertia <= 0):
        raise ValueError(f"need finite omega and positive finite inertia, got {omega}, {inertia}")
    x = np.concatenate([omega, inertia])
    return rank_analysis(observability_matrix(x, order), euler_scale(x), rtol, sign_component=3)


# --------------------------------------------------------------------------- filter state (Gramian)
#
# The local observability of the whole filter state x = [rho, rho_dot, omega, q, P_1..P_N,
# k1, k2] along a trajectory, from the discrete observability Gramian of the linearized
# model (the filter's own Jacobians F, H at the true states):
#
#     W = sum_k Phi(t_k, t_0)^T H_k^T R_k^-1 H_k Phi(t_k, t_0)
#
# ``delta x_0^T W delta x_0`` is the squared whitened change of all measurements caused by
# an initial perturbation ``delta x_0`` (to first order); ``W`` is the Fisher information
# about ``x_0`` from the measurements, so ``(W + P0^-1)^-1`` is the (linearized, no
# process noise) Cramer-Rao bound on the posterior covariance of ``x_0``.


def cumulative_transitions(step_transitions: Array) -> Array:
    """``Phi(t_k, t_0)`` ``(..., K+1, n, n)`` from the one-step ``Phi(t_{k+1}, t_k)`` ``(..., K, n, n)``.

    ``Phi(t_0, t_0) = I`` and ``Phi(t_{k+1}, t_0) = Phi(t_{k+1}, t_k) Phi(t_k, t_0)``.
    """
    steps = np.asarray(step_transitions, dtype=float)
    if steps.ndim < 3 or steps.shape[-1] != steps.shape[-2]:
        raise ValueError(f"step transitions must be (..., K, n, n), got shape {steps.shape}")
    batch, K, n = steps.shape[:-3], steps.shape[-3], steps.shape[-1]
    out = np.empty(batch + (K + 1, n, n))
    out[..., 0, :, :] = np.eye(n)
    for k in range(K):
        out[..., k + 1, :, :] = steps[..., k, :, :] @ out[..., k, :, :]
    return out


def whitened_observability_matrix(step_transitions: Array, H: Array, weights: Array) -> Array:
    """The stacked rows ``sqrt(w_k) H_k Phi(t_k, t_0)`` ``(..., (K+1) m, n)``, so ``W = O_w^T O_w``.

    ``H (..., K+1, m, n)``: the measurement Jacobians at ``t_0..t_K`` (a fixed number ``m``
    of rows per time: rows that are absent at a time, e.g. invisible features, get weight
    0); ``weights (..., K+1, m)``: the inverse noise variances ``1 / sigma^2`` (``R_k`` is
    diagonal), 0 for absent rows.
    """
    H = np.asarray(H, dtype=float)
    w = np.asarray(weights, dtype=float)
    if H.ndim < 3 or w.shape != H.shape[:-1]:
        raise ValueError(f"H (..., K+1, m, n) and weights (..., K+1, m) do not match: {H.shape}, {w.shape}")
    if np.any(w < 0) or not np.all(np.isfinite(w)):
        raise ValueError("weights (inverse variances) must be finite and >= 0")
    Phi = cumulative_transitions(step_transitions)
    if Phi.shape[-3] != H.shape[-3] or Phi.shape[-1] != H.shape[-1]:
        raise ValueError(f"{Phi.shape[-3] - 1} transitions and {H.shape[-3]} measurement times do not match")
    rows = np.sqrt(w)[..., None] * (H @ Phi)
    return rows.reshape(rows.shape[:-3] + (rows.shape[-3] * rows.shape[-2], rows.shape[-1]))


def observability_gramian(step_transitions: Array, H: Array, weights: Array) -> Array:
    """``W = sum_k Phi(t_k,t_0)^T H_k^T diag(w_k) H_k Phi(t_k,t_0)`` ``(..., n, n)``, symmetric.

    Arguments as in :func:`whitened_observability_matrix`; ``W = O_w^T O_w``.
    """
    O = whitened_observability_matrix(step_transitions, H, weights)
    W = np.swapaxes(O, -1, -2) @ O
    return 0.5 * (W + np.swapaxes(W, -1, -2))


def filter_state_names(n_points: int) -> tuple[str, ...]:
    """``rho_x, ..., rho_dot_x, ..., omega_x, ..., q0..q3, P1_x, ..., PN_z, k1, k2``."""
    xyz = ("x", "y", "z")
    names = [f"{b}_{a}" for b in ("rho", "rho_dot", "omega") for a in xyz]
    names += [f"q{i}" for i in range(4)]
    names += [f"P{i + 1}_{a}" for i in range(n_points) for a in xyz]
    return tuple(names + ["k1", "k2"])


def quaternion_norm_direction(x: Array) -> Array:
    """``e_q = [0, 0, 0, q, 0, ..., 0]`` ``(..., n)``: scaling ``q`` changes neither ``f``'s
    attitude (``D(q)`` is normalized) nor ``h``, so ``H e_q = 0`` and, along the true flow,
    ``Phi(t, t_0) e_q(t_0) = e_q(t)`` (``F e_q = [0, 0, 0, q', 0]``): unobservable by construction."""
    x = np.asarray(x, dtype=float)
    out = np.zeros_like(x)
    out[..., QUAT] = x[..., QUAT]
    return out


def gauge_directions(x: Array) -> Array:
    """The body-frame gauge ``(..., n, 3)``: column ``j`` rotates the body frame by a small
    angle about its axis ``j`` and the feature points with it:

        delta q = 1/2 Q(q) e_j  (q -> q (x) [1, e_j/2]),   delta P_i = P_i x e_j

    so ``D(q) P_i`` and every image are unchanged to first order (``H g_j = 0``). Only the
    dynamics see it: the inertia is diagonal in the body frame, so rotating that frame
    changes Euler's equations unless the target spins about a principal axis or is spherical.
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[-1]
    N = n_points_of(n)
    Q = omega_matrix(x[..., QUAT])  # (..., 4, 3)
    P = x[..., POINTS0 : POINTS0 + 3 * N].reshape(x.shape[:-1] + (N, 3))
    out = np.zeros(x.shape + (3,))
    out[..., QUAT, :] = 0.5 * Q
    for j in range(3):
        e = np.zeros(3)
        e[j] = 1.0
        out[..., POINTS0 : POINTS0 + 3 * N, j] = np.cross(P, e).reshape(x.shape[:-1] + (3 * N,))
    return out


def com_shift_directions(x: Array) -> Array:
    """Moving the centre of mass inside the feature cloud ``(..., n, 3)``: column ``j`` is

        delta P_i = e_j (all i),   delta rho = -D e_j,   delta rho_dot = -omega x (D e_j)

    which leaves every ``rho_i = rho + D P_i`` and ``rho_dot_i = rho_dot + omega x D P_i``
    (so every image) unchanged at ``t_0``. Only the motion reveals the centre of mass (the
    centre of the rotation), so these directions are weak at slow spin.
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[-1]
    N = n_points_of(n)
    D = dcm(x[..., QUAT])  # (..., 3, 3)
    w = x[..., 6:9]
    out = np.zeros(x.shape + (3,))
    out[..., 0:3, :] = -D
    out[..., 3:6, :] = -np.cross(w[..., None, :], np.swapaxes(D, -1, -2)).swapaxes(-1, -2)
    for i in range(N):
        out[..., POINTS0 + 3 * i : POINTS0 + 3 * i + 3, :] = np.eye(3)
    return out


def scaled_basis(directions: Array, scale: Array) -> Array:
    """Orthonormal basis ``(n, r)`` of ``span(S^-1 directions)``, ``S = diag(scale)``: the
    directions ``(n, r)`` expressed in the scaled coordinates ``z = S^-1 delta x``."""
    d = np.asarray(directions, dtype=float)
    if d.ndim == 1:
        d = d[:, None]
    Q, _ = np.linalg.qr(d / np.asarray(scale, dtype=float)[:, None])
    return Q


@dataclass(frozen=True)
class GramianEigen:
    """Result of :func:`gramian_eigen` (everything in the scaled coordinates ``z = S^-1 delta x``).

    ``eigenvalues``: ascending, of ``W~ = S W S`` restricted to the complement of ``fixed``;
    ``eigenvectors``: ``(n, n - r)`` unit columns (``S`` times a column is the physical
    direction); ``lambda_max``: the largest eigenvalue; ``floor``: ``n eps lambda_max``,
    below which an eigenvalue is zero to round-off; ``fixed``: the ``(n, r)`` orthonormal
    directions projected out, with their Rayleigh quotients ``fixed_rayleigh = u^T W~ u``.
    """

    eigenvalues: Array
    eigenvectors: Array
    lambda_max: float
    floor: float
    fixed: Array
    fixed_rayleigh: Array
    scaled_gramian: Array


def gramian_eigen(W: Array, scale: Array, fixed: Array | None = None) -> GramianEigen:
    """Eigen-decomposition of one Gramian ``W (n, n)`` in scaled, unit-free coordinates.

    ``W~ = S W S`` with ``S = diag(scale)`` (a characteristic size of each state component:
    ``z^T W~ z`` is the whitened squared measurement change for a step of ``z`` such sizes).
    With ``B`` an orthonormal basis of the complement of the orthonormal columns ``fixed``
    (``(n, r)``, scaled coordinates, e.g. the quaternion-norm direction), the eigenpairs of
    ``B^T W~ B`` (``np.linalg.eigh``, ascending) mapped back by ``B``.
    """
    W = np.asarray(W, dtype=float)
    s = np.asarray(scale, dtype=float)
    n = W.shape[-1]
    if W.shape != (n, n) or s.shape != (n,):
        raise ValueError(f"gramian_eigen takes one (n, n) Gramian and (n,) scales, got {W.shape}, {s.shape}")
    if np.any(~np.isfinite(s)) or np.any(s <= 0) or not np.all(np.isfinite(W)):
        raise ValueError("the Gramian must be finite and the scales positive and finite")
    Ws = s[:, None] * W * s[None, :]
    Ws = 0.5 * (Ws + Ws.T)
    U = np.zeros((n, 0)) if fixed is None else np.asarray(fixed, dtype=float).reshape(n, -1)
    r = U.shape[1]
    if r and not np.allclose(U.T @ U, np.eye(r), atol=1e-10):
        raise ValueError("fixed directions must be orthonormal columns (use scaled_basis)")
    full, _, _ = np.linalg.svd(U, full_matrices=True) if r else (np.eye(n), None, None)
    B = full[:, r:]
    lam, Y = np.linalg.eigh(B.T @ Ws @ B)
    V = B @ Y
    V = np.stack([_fix_sign(V[:, i], int(np.argmax(np.abs(V[:, i])))) for i in range(V.shape[1])], axis=1)
    lam_max = float(np.linalg.eigvalsh(Ws)[-1])
    rayleigh = np.einsum("ir,ij,jr->r", U, Ws, U)
    return GramianEigen(
        eigenvalues=lam,
        eigenvectors=V,
        lambda_max=lam_max,
        floor=float(n * np.finfo(float).eps * lam_max),
        fixed=U,
        fixed_rayleigh=rayleigh,
        scaled_gramian=Ws,
    )


def describe_direction(v: Array, names, min_abs: float = 0.1, max_terms: int = 6) -> list[tuple[str, float]]:
    """The largest components of a unit direction ``v`` by name, in decreasing magnitude:
    those with ``|v_i| >= min_abs`` (at least one, at most ``max_terms``)."""
    v = np.asarray(v, dtype=float)
    order = np.argsort(-np.abs(v), kind="stable")
    keep = [i for i in order[:max_terms] if abs(v[i]) >= min_abs] or [int(order[0])]
    return [(names[i], float(v[i])) for i in keep]


def subspace_share(v: Array, basis: Array) -> float:
    """``|B^T v|^2 / |v|^2``: the fraction of ``v`` in the span of the orthonormal columns ``B``."""
    v = np.asarray(v, dtype=float)
    return float(np.sum((np.asarray(basis).T @ v) ** 2) / np.dot(v, v))


def crlb_covariance(W: Array, prior_diag: Array, no_prior: Array | None = None) -> Array:
    """``(W + P0^-1)^-1`` ``(n, n)`` for a diagonal prior ``P0 = diag(prior_diag)``.

    Computed in the scaled coordinates ``S = diag(sqrt(prior_diag))``, where the information
    is ``J~ = S W S + I`` (well scaled), by its Cholesky factor. ``no_prior`` (boolean
    ``(n,)``) drops the prior of those components (their ``1`` on the diagonal), e.g. to see
    what the measurements alone say about ``k`` given the prior on the rest; ``J~`` must
    then still be positive definite.

    NOTE: this forms an inverse (Cholesky solve with the identity's columns). That is
    acceptable here ONLY because the result is a report (its diagonal and small blocks);
    no estimator uses it.
    """
    from scipy.linalg import cho_factor, cho_solve

    W = np.asarray(W, dtype=float)
    p = np.asarray(prior_diag, dtype=float)
    n = W.shape[-1]
    if W.shape != (n, n) or p.shape != (n,) or np.any(~np.isfinite(p)) or np.any(p <= 0):
        raise ValueError("crlb_covariance takes one (n, n) W and (n,) positive prior variances")
    s = np.sqrt(p)
    J = s[:, None] * W * s[None, :]
    d = np.ones(n) if no_prior is None else np.where(np.asarray(no_prior, bool), 0.0, 1.0)
    J = 0.5 * (J + J.T) + np.diag(d)
    C = cho_solve(cho_factor(J, lower=True), np.eye(n))
    return s[:, None] * C * s[None, :]


def crlb_sigma(W: Array, prior_diag: Array, no_prior: Array | None = None) -> Array:
    """``sqrt(diag((W + P0^-1)^-1))`` ``(n,)`` (see :func:`crlb_covariance`)."""
    return np.sqrt(np.diag(crlb_covariance(W, prior_diag, no_prior)))
