"""Feature slots: the state's ``N`` point blocks hold whichever tracks the tracker delivers (docs/filters.md, Slots).

A slot is *occupied* while one track lives in it. When a new track takes a slot (``born``), the slot's point is
initialized from that track's first stereo measurement and the current pose estimate, the standard landmark
initialization of SLAM; when its track ends, the slot is *freed*: its block is reset (no correlation with the
rest, the prior variance) and it is not measured until a new track is born in it. The idealized point model is
the special case of ``N`` slots occupied from the start by the same ``N`` tracks (no birth, no freeing).

Everything here works in the attitude chart of ``core.errorstate`` (points are additive coordinates there, the
attitude error ``a`` is in ``L``: ``D(q) = (I + [a x]) D(q_ref)``); a filter whose covariance lives in the aligned
chart has it mapped there and back (``core.aligned``: exact at first order, the same state around the same point).

**Triangulation** (docs/model.md, Stereo measurements; focal length ``f``: 1 in normalized units): with the right
camera at the leader's centre and the left one at ``+b`` along ``x``,

    y = -f b / (u_L - u_R),   x = u_R y / f,   z = (v_R + v_L) y / (2 f)

and its Jacobian ``J = d p / d (u_R, v_R, u_L, v_L)``.

**Birth** of slot ``j`` from the triangulated point ``p`` (in ``L``) with image noise ``R_y``:

    P_j = D(q)^T (p - rho)
    dP_j = G_x eps + G_y dy,   G_x: d rho -> -D^T,  a -> D^T [v x]  (v = p - rho),   G_y = D^T J
    P_jj = G_x P G_x^T + G_y R_y G_y^T,   P_j,other = G_x P_:,other

(the old point's rows and columns are dropped first: ``G_x`` has no column for it, so the new point's covariance
never depends on what the slot held).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..core import aligned
from ..core import errorstate as es
from ..core import initialization as ini
from ..core import layout as lay
from ..core import quaternion as qt
from ..core import state as st

Array = NDArray[np.float64]

IMAGE = slice(0, 4)  # u_R, v_R, u_L, v_L among a feature's channels (core.camera.project)
FREED_VARIANCE = 1.0  # m^2: a free slot's variance per axis (unused by any measurement; only conditioning)


@dataclass(frozen=True)
class Schedule:
    """Which track each slot holds over a chunk's trials (``B`` trials, ``K+1`` steps, ``N`` slots).

    ``occupied``: a track lives in the slot at the step; ``born``: a new track entered it at the step (its
    measurement then initializes the slot and is not used by the update); ``truth (B, K+1, N, 3)``: the true body
    point of the slot's track (NaN where unknown: such a slot is left out of the NEES).
    """

    occupied: NDArray[np.bool_]
    born: NDArray[np.bool_]
    truth: Array

    def freed(self, k: int) -> NDArray[np.bool_]:
        """``(B, N)``: the slot's track ended at step ``k`` (occupied at ``k-1``, not at ``k``)."""
        if k == 0:
            return np.zeros_like(self.occupied[:, 0])
        return self.occupied[:, k - 1] & ~self.occupied[:, k]

    def true_state(self, x_true: Array, k: int, rows: NDArray[np.int64]) -> Array:
        """``x_true`` (``(n,)`` or ``(len(rows), n)``) of trials ``rows`` at step ``k`` with each slot's true point."""
        n = x_true.shape[-1]
        N = self.truth.shape[2]
        xt = np.array(np.broadcast_to(x_true, (rows.size, n)))
        xt[:, lay.POINTS : lay.point(N)] = self.truth[rows, k].reshape(rows.size, lay.VEC * N)
        return xt


def triangulate(y: Array, baseline: float, focal: float = 1.0) -> tuple[Array, Array]:
    """Point ``p (..., 3)`` in ``L`` from one feature's channels ``y (..., >=8)`` (``core.initialization.triangulate``),
    and ``J (..., 3, 4)``.

    ``y = -f b / (u_L - u_R)``, ``x = u_R y / f``, ``z = (v_R + v_L) y / (2 f)``; ``J`` is
    ``d p / d (u_R, v_R, u_L, v_L)``.
    """
    p = ini.triangulate(y, baseline, focal)[0]
    u_r, v_r, u_l, v_l = (y[..., c] for c in range(4))
    d = u_l - u_r
    py = p[..., 1]
    v = 0.5 * (v_r + v_l)
    dy_dd = focal * baseline / (d * d)  # d py / d (u_L - u_R)
    J = np.zeros(y.shape[:-1] + (3, 4))
    J[..., 1, 0], J[..., 1, 2] = -dy_dd, dy_dd
    J[..., 0, 0] = (py - u_r * dy_dd) / focal
    J[..., 0, 2] = u_r * dy_dd / focal
    J[..., 2, 0], J[..., 2, 2] = -v * dy_dd / focal, v * dy_dd / focal
    J[..., 2, 1] = J[..., 2, 3] = 0.5 * py / focal
    return p, J


def birth_point(x: Array, p: Array) -> Array:
    """The body-frame point ``D(q)^T (p - rho) (..., 3)`` of a point ``p`` in ``L`` seen from the state ``x``."""
    D = qt.dcm(x[..., st.QUAT])
    return qt.matvec(np.swapaxes(D, -1, -2), p - x[..., st.RHO])


def birth_jacobians(x: Array, p: Array, J: Array) -> tuple[Array, Array]:
    """``G_x (..., 3, n-1)`` in the attitude chart and ``G_y (..., 3, 4)``: the new point's linearized error.

    ``dP_j = -D^T d rho + D^T [v x] a + D^T J dy`` with ``v = p - rho`` (module docstring).
    """
    n = x.shape[-1]
    Dt = np.swapaxes(qt.dcm(x[..., st.QUAT]), -1, -2)
    v = p - x[..., st.RHO]
    G = np.zeros(x.shape[:-1] + (3, n - 1))
    G[..., :, lay.E_RHO : lay.E_RHO + lay.VEC] = -Dt
    G[..., :, es.ATT] = Dt @ qt.skew(v)
    return G, Dt @ J


def _attitude(x: Array, P: Array, chart: str) -> Array:
    if chart == "aligned":
        return aligned.to_attitude_chart(x, P)
    if chart == "attitude":
        return P.copy()
    raise ValueError(f"feature slots need an error-state filter (attitude or aligned chart), not '{chart}'")


def _back(x: Array, P: Array, chart: str) -> Array:
    return aligned.from_attitude_chart(x, P) if chart == "aligned" else P


def _free(P: Array, b: int, rows: slice) -> None:
    """Reset the block ``rows`` of ``P[b]`` in place: no correlation, ``FREED_VARIANCE`` on the diagonal."""
    P[b, rows, :] = 0.0
    P[b, :, rows] = 0.0
    P[b, rows, rows] = FREED_VARIANCE * np.eye(lay.VEC)


def manage(x: Array, P: Array, chart: str, born: NDArray[np.bool_], freed: NDArray[np.bool_], y: Array,
           image_var: Array, baseline: float, focal: float = 1.0) -> tuple[Array, Array]:  # fmt: skip
    """The slots' births and frees of one step on ``(x (B, n), P (B, n-1, n-1))`` in ``chart``.

    ``born (B, N)``: a new track enters the slot, measured by ``y (B, N, >=4)`` (its first stereo image
    coordinates, noise variances ``image_var (4,)``); ``freed (B, N)``: the slot's track ended (and none is born).
    Returns new arrays (``x, P`` themselves at a step without an event); trials with no event keep their bits.
    """
    rows = np.flatnonzero(born.any(axis=1) | freed.any(axis=1))
    if rows.size == 0:
        return x, P
    x, P = x.copy(), P.copy()
    xs = x[rows]
    Pa = _attitude(xs, P[rows], chart)
    N = born.shape[1]
    for j in range(N):
        ej = slice(lay.e_point(j), lay.e_point(j + 1))
        for b in np.flatnonzero(freed[rows, j] & ~born[rows, j]):
            _free(Pa, b, ej)
        bj = np.flatnonzero(born[rows, j])
        if bj.size == 0:
            continue
        p, J = triangulate(y[rows[bj], j], baseline, focal)
        Gx, Gy = birth_jacobians(xs[bj], p, J)
        Pb = Pa[bj]
        Pb[:, ej, :] = 0.0  # the old point leaves: G_x has no column for it
        Pb[:, :, ej] = 0.0
        M = Gx @ Pb  # (b, 3, n-1): the new point's cross-covariance with everything
        Pjj = M @ np.swapaxes(Gx, -1, -2) + (Gy * image_var[None, None, :]) @ np.swapaxes(Gy, -1, -2)
        M[:, :, ej] = 0.5 * (Pjj + np.swapaxes(Pjj, -1, -2))
        Pb[:, ej, :] = M
        Pb[:, :, ej] = np.swapaxes(M, -1, -2)
        Pa[bj] = Pb
        xs[bj, lay.point(j) : lay.point(j + 1)] = birth_point(xs[bj], p)
    x[rows] = xs
    P[rows] = _back(xs, Pa, chart)
    return x, P


def _reduced(n: int, keep: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Indices into the state and the error state of a state that keeps only the points ``keep``."""
    N = (n - lay.FIXED) // lay.VEC
    pts = [np.arange(lay.point(j), lay.point(j + 1)) for j in keep]
    e_pts = [np.arange(lay.e_point(j), lay.e_point(j + 1)) for j in keep]
    k_x = np.arange(lay.point(N), n)
    k_e = np.arange(lay.e_point(N), n - 1)
    return (np.concatenate([np.arange(lay.POINTS), *pts, k_x]).astype(np.int64),
            np.concatenate([np.arange(lay.E_POINTS), *e_pts, k_e]).astype(np.int64))  # fmt: skip


def nees(x_hat: Array, P: Array, chart: str, x_true: Array, occupied: NDArray[np.bool_]) -> tuple[dict[str, Array],
                                                                                                     dict[str, Array]]:
    """Full, per-block and gauge-projected NEES over the *occupied* slots, and their degrees of freedom (``(B,)`` each).

    The NEES of the state without the free slots: the marginal of the others (the covariance mapped to the attitude
    chart, where the points are coordinates of their own, the free slots' rows and columns dropped), reported as
    ``core.aligned.nees_report`` reports every filter's (full and gauge-projected NEES in the aligned chart of the
    kept points, blocks in the attitude chart). ``occupied (B, N)``: a slot whose true point is unknown (NaN in
    ``x_true (B, n)``) counts as free. Trials with the same kept slots are evaluated together; a trial without one
    kept slot gets NaN.
    """
    B, n = x_hat.shape
    N = st.n_points(n)
    Pa = _attitude(x_hat, P, chart)
    xt = np.broadcast_to(x_true, x_hat.shape)
    kept = occupied & np.isfinite(xt[:, lay.POINTS : lay.point(N)].reshape(B, N, lay.VEC)).all(-1)
    out = {k: np.full(B, np.nan) for k in es.nees_dof(n)}
    dof = {k: np.zeros(B, np.int64) for k in es.nees_dof(n)}
    pats, inverse = np.unique(kept, axis=0, return_inverse=True)
    for c, pat in enumerate(pats):
        rows = np.flatnonzero(inverse.ravel() == c)
        keep = np.flatnonzero(pat)
        if keep.size == 0:
            continue
        ix, ie = _reduced(n, keep)
        xr = x_hat[rows][:, ix]
        Pr = Pa[rows][:, ie][:, :, ie]
        M = aligned.attitude_map(xr)  # (one map for the two: the same numbers)
        v = aligned.nees_report(xr, aligned.from_attitude_chart(xr, Pr, M), xt[rows][:, ix], M)
        for k, d in es.nees_dof(ix.size).items():
            out[k][rows] = v[k]
            dof[k][rows] = d
    return out, dof
