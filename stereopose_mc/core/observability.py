"""Local nonlinear observability: the Hermann-Krener rank test (thesis ch. 4).

Two layers:

1. **Generic linear algebra** (:func:`rank_analysis`): the numerical rank, the singular
   values and an orthonormal basis of the null space (the locally unobservable
   directions) of any observability-type matrix ``O`` (rows: gradients of observed
   functions, columns: state components). Columns are scaled by a typical magnitude of
   each state component and rows are equilibrated before the SVD, so the rank decision
   does not depend on the units the state happens to be written in. The same function
   serves any other observability matrix, e.g. an observability Gramian built from a
   filter's ``F`` and ``H`` along a trajectory (to be added beside the Euler functions
   below, reusing :func:`rank_analysis` unchanged).

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

All kernels take any leading batch axes ``(...)``; :func:`rank_analysis` works on one
matrix (its null space has a data-dependent number of columns).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

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
