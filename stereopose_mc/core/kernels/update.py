"""Compiled (Numba) EKF and IEKF measurement updates on the row-sparse ``H`` of the model.

Twins of ``core.kalman.ekf_update`` and ``core.kalman.iekf_update`` (whose docstrings give
the equations), fused with the measurement model of ``core.kernels.model`` and run one
trial at a time: every product with ``H`` touches only the 16 non-zero columns of a row
(a feature's rows see ``rho, rho_dot, omega, q`` and its own point; the pseudo rows
``omega, q, k``), the symmetric positive definite systems (the whitened ``A = I + Hw^T Hw``
of both updates, the EKF being one Gauss-Newton step of the IEKF, and ``P-`` itself) are
solved by Cholesky factorizations (LAPACK's ``potrf`` in place, ``_cholesky``; past ``LARGE_N`` columns by
blocks of rows around BLAS products, ``cholesky._upper_blocked``, faster there); ``P+`` is the
Joseph form of the numpy path evaluated for the optimal gain (``L A^-1 L^T``, positive
semi-definite by construction: the same matrix to round-off, exactly symmetric); the IEKF's iterations,
step control (line search on the MAP cost with step halving, or Levenberg-Marquardt's damped
steps) and unit-free stopping test run per trial.

Both kernels take the filter's ``chart``: 0, the full state (``filters.relnav``: ``x + dx``,
quaternion renormalized); 1, the aligned error state (``filters.mekf`` with
``core.aligned``: prior ``e = 0`` with the error-state ``P``, ``h(x- [+] e)``, the row-sparse
``H_e`` of ``core.kernels.aligned`` whose virtual columns are served by the point sums
appended to ``P`` or ``L`` (``_with_virtual``), reset ``x+ = x- [+] e+``); 2, the attitude
error state (``filters.mekf`` with ``core.errorstate``: the same, with the row-sparse ``H_e`` of
``core.kernels.attitude`` and no virtual columns).

A measurement row with ``mask = False`` (a feature dropped by the tracker or rejected by
the gate) is taken out of the update exactly as ``filters.gating.masked_measure`` does:
``h = y`` and ``H = 0`` on that row.

Past ``LARGE_N`` (64) columns the update exploits more structure (growth with the number of
points): ``A`` is formed from the arrow-shaped information ``H^T R^-1 H`` (``whiten._whiten_information``:
``I + L^T Y L`` by strips, no ``m n^2`` Gram product of the rows), the aligned chart is whitened in
centered point coordinates (``_center_cov``: the points' mean and their deviations, so that
the unmeasured centroid does not cancel in the product). Up to 64 columns (case B's 29; 20
points) the kernels do without: there the extra passes cost more than they save.

At every size ``A`` is factorized in reverse order (``triangular._factor``), so that ``P+ = L A^-1 L^T =
M M^T`` with ``M`` lower triangular (``triangular._posterior_covariance_rev``): ``P+``'s own Cholesky
factor comes with it, which the kernels return (as ``J M^T``) for the NEES to use instead of
factorizing ``P+`` again (``core.kernels.consistency.nees_batch``); in the centred coordinates ``M`` is the factor
of ``T P+ T^T`` (none returned), with which the kernels' own NEES evaluate those of ``T e`` (``consistency._one``).
Given the true states (``x_true``, the engine's runs: ``mc.trial``), the kernels evaluate each posterior's NEES
themselves as soon as ``P+`` and its square root are formed (``consistency._nees_one``, the per-trial body of
``nees_batch``, or for the full state ``consistency._nees_given``, its path with the square root given: the same
numbers), while they are still in cache (a separate pass over the batch would read them again from memory). The
square root then stays in a scratch array and is not returned (nothing else reads it: a ``(B, n, n)`` output is
memory traffic for nothing).

Each kernel returns ``ok (B,)``: False where a Cholesky factorization failed (the numpy
path raises ``LinAlgError`` there; the caller handles those trials the numpy way).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..layout import CHART_ALIGNED, CHART_FULL, QUAT, VEC
from . import attitude as _att
from ._refs import borrow, keep
from .aligned import _chart, _e_n_points, _measure_aligned, virtual_rows
from .centred import _center_cov, _centered_model_rows, _centered_virtual_rows, _sqrt_mul, _uncenter_cov
from .cholesky import _cholesky, _cholesky_t, _cholesky_tu
from .consistency import N_AXES, _axis_row, _nees_given, _nees_one, _nees_scratch
from .model import NNZ, Q_END, _measure_one
from .rows import _dot, _pair_products
from .triangular import _factor, _posterior_covariance_rev, _solve
from .whiten import LARGE_N, _whiten_g, scratch_sizes

_JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")

# the IEKF's step control and stopping rule (``kalman.iekf_update``'s options), as the kernels take them
CONTROL_NONE, CONTROL_LINE_SEARCH, CONTROL_LM = 0, 1, 2  # plain Gauss-Newton; line search; Levenberg-Marquardt
STOP_MAHALANOBIS, STOP_PRIOR, STOP_SCALED, STOP_RAW = 0, 1, 2, 3  # |dz|_A; |dz|; max |dx_i| / sigma_i; |dx|
STOPPING = {"mahalanobis": STOP_MAHALANOBIS, "prior": STOP_PRIOR, "scaled": STOP_SCALED, "raw": STOP_RAW}
CONTROL = {"none": CONTROL_NONE, "line_search": CONTROL_LINE_SEARCH, "levenberg_marquardt": CONTROL_LM}



@njit(**_JIT)
def _masked(hx, Hval, y, mask):
    """Rows out of the update: ``h = y``, ``H = 0``."""
    for r in range(hx.shape[0]):
        if not mask[r]:
            hx[r] = y[r]
            for k in range(NNZ):
                Hval[r, k] = 0.0


@njit(**_JIT)
def _linearization(hx, Hval, cols, yb, mask, rws, Laug, Hw, rw, A, g, ws, wi, upper, cen, Hc, cc, N):
    """The whitened system of one iterate from its ``h`` and row-sparse ``H`` (``_measure_at``): the masked rows
    taken out (``_masked``), then ``Hw``, ``rw``, ``g`` and ``A`` (``whiten._whiten_g``), or in the centred
    coordinates (``cen``: ``centred._centered_model_rows`` into ``Hc``, ``cc``, then ``whiten._whiten_g``)."""
    _masked(hx, Hval, yb, mask)
    if cen:
        _centered_model_rows(Hval, cols, Hc, cc, A.shape[0], N)
        _whiten_g(hx, Hc, cc, yb, rws, Laug, Hw, rw, A, g, ws, wi, upper)
    else:
        _whiten_g(hx, Hval, cols, yb, rws, Laug, Hw, rw, A, g, ws, wi, upper)


@njit(**_JIT)
def _measure_at(chart, xp, e, model, alpha, compute_jac, hx, Hval, xt, D, dD):
    """``h`` and the row-sparse ``H`` of one trial at ``x- [+] e`` in the filter's coordinates.

    ``chart`` 0: the full state, ``xt = x- + e``, ``H`` of ``model._measure_one``; 1: the aligned
    error state, ``xt = aligned.chart(x-, e)``, ``H_e`` of ``aligned._measure_aligned``; 2: the
    attitude error state, ``xt = errorstate.chart(x-, e)``, ``H_e`` of ``attitude._measure_attitude``.
    """
    if chart == CHART_FULL:
        for i in range(xp.shape[0]):
            xt[i] = xp[i] + e[i]
        _measure_one(xt, model, alpha, compute_jac, hx, Hval, D, dD)
    elif chart == CHART_ALIGNED:
        _measure_aligned(xp, e, model, alpha, compute_jac, hx, Hval, xt, D, dD)
    else:
        _att._measure_attitude(xp, e, model, alpha, compute_jac, hx, Hval, xt, D, dD)


@njit(**_JIT)
def _reset(chart, xp, e, out, D, dD):
    """The posterior state ``x- [+] e``: ``x- + e`` with its quaternion renormalized (full), ``aligned.chart`` or
    ``errorstate.chart``. ``D (3, 3)``, ``dD (4, 3, 3)``: scratch (``aligned.chart``'s)."""
    if chart == CHART_FULL:
        for i in range(xp.shape[0]):
            out[i] = xp[i] + e[i]
        _normalize_q(out)
    elif chart == CHART_ALIGNED:
        _chart(xp, e, out, D, dD[0], dD[1, 0])
    else:
        _att._chart(xp, e, out)


@njit(**_JIT)
def _with_virtual(chart, Maug):
    """In the aligned chart, the rows of the virtual columns appended to ``M = Maug[:n]`` in place
    (``aligned.virtual_rows``: ``Maug[n + a] = sum_j M[12 + 3 j + a]``); nothing in the other charts."""
    if chart == CHART_ALIGNED:
        n = Maug.shape[1]
        virtual_rows(Maug[:n], Maug)


def ekf_update_batch(x, P, y, R, mask, model, alpha, cols, chart, x_true=None, attitude=False):
    """EKF update of every trial: ``S = H P H^T + R``, ``K = P H^T S^-1``, ``x+ = x [+] K nu``, ``P+``.

    ``model``: the step's ``model.StepModel`` (visible features, camera, pseudo rows), ``alpha (B, 3)`` the
    trials' measured accelerations, ``cols`` the columns of the row-sparse ``H``, ``mask (B, m)`` the rows that
    enter the update (module docstring).

    ``chart`` 0: ``x``, ``P (B, n, n)`` of the full state (``relnav.update``); 1: ``P (B, n-1, n-1)``
    of the aligned error state at ``x`` (``mekf.update``: prior ``e = 0``, ``H_e``, reset
    ``x+ = x [+] e+``); 2: the same in the attitude error state. Evaluated as one Gauss-Newton
    step of ``iekf_update_batch`` from the prior (whitened, ``P = L L^T``, ``Hw = R^-1/2 H L``,
    ``A = I + Hw^T Hw``): by the matrix inversion lemma ``L A^-1 Hw^T R^-1/2 = P H^T S^-1 = K``,
    ``L A^-1 L^T = P - K S K^T`` (the Joseph form of ``kalman.ekf_update`` for its optimal gain)
    and ``nu^T S^-1 nu = |rw|^2 - g^T A^-1 g``: the same numbers to round-off, with an
    ``n x n`` system instead of the ``m x m`` one (``m = 8N + 3 > n = 3N + 15``).

    A Python call of the compiled ``iekf_update_batch`` with one plain Gauss-Newton step (not a
    kernel of its own: that was a second copy of the same machine code to load at start-up).

    Returns ``(x+, P+, nu, nis, ok, R+, nees)`` (``R+``, ``x_true``, ``attitude`` and ``nees`` as
    ``iekf_update_batch``'s); in the full chart the quaternion of ``x+`` is renormalized.
    """
    xt = np.empty((0, x.shape[1])) if x_true is None else x_true
    xo, Po, nu, nis, _, _, ok, Ro, ev = iekf_update_batch(x, P, y, R, mask, model, alpha, cols, chart, 0.0, 1,
                                                          CONTROL_NONE, STOP_PRIOR, 0, xt, attitude)  # fmt: skip
    return xo, Po, nu, nis, ok, Ro, ev


@njit(**_JIT)
def _normalize_q(x):
    qn = math.sqrt(x[QUAT] * x[QUAT] + x[QUAT + 1] * x[QUAT + 1] + x[QUAT + 2] * x[QUAT + 2]
                   + x[QUAT + 3] * x[QUAT + 3])  # fmt: skip
    for i in range(QUAT, Q_END):
        x[i] = x[i] / qn


@njit(**_JIT)
def _cost_at(chart, z, xp, L, yb, rws, mask, model, alpha, e, xt, hx, H, D, dD, compute_jac, cen, N, tmp):
    """MAP cost ``|z|^2 + |R^-1/2 (y - h(x- [+] L z))|^2``; ``h`` in ``hx``, and ``H`` too when ``compute_jac``
    (``cen``: ``L = T^-1 L'``, ``_sqrt_mul`` through ``tmp``)."""
    _sqrt_mul(L, z, e, cen, N, tmp)
    _measure_at(chart, xp, e, model, alpha, compute_jac, hx, H, xt, D, dD)
    c = 0.0
    for i in range(z.shape[0]):
        c += z[i] * z[i]
    for r in range(hx.shape[0]):
        if mask[r]:
            e = (yb[r] - hx[r]) * rws[r]
            c += e * e
    return c


@njit(**_JIT)
def _row_products(A, v, out):
    """``out = A v`` row by row, ``out[i] = _dot_row(A, i, v, 0, n)``, two rows per pass (``rows._pair_products``)."""
    _pair_products(A, v, out, False)


@njit(**_JIT)
def _keep_linearization(A, Afin):
    """Copy the prior's ``A = I + Hw^T Hw`` (the first iterate's, kept in case the first step is rejected; an accepted
    later iterate's is kept by swapping the two buffers). The ``A`` of the last accepted step gives ``P+``."""
    Afin[:, :] = A


@njit(**_JIT)
def iekf_update_batch(x, P, y, R, mask, model, alpha, cols, chart, tol, max_iter, control, stopping, max_halvings,
                      x_true, attitude):  # fmt: skip
    """Gauss-Newton IEKF in whitened coordinates ``x = x- [+] L z`` (``kalman.iekf_update``), per trial.

    ``chart`` as in ``ekf_update_batch`` (1: the iterates are ``aligned.chart(x-, L z)``, ``P`` that
    of the aligned error state, as ``mekf.update``; 2: ``errorstate.chart(x-, L z)``, the
    attitude error state's); ``control``: 0 none, 1 line search, 2 Levenberg-Marquardt (``lam``
    from 1e-3, /10 after an accepted step, x10 after a rejected one, as ``kalman.iekf_update``);
    ``stopping``: 0 mahalanobis, 1 prior, 2 scaled, 3 raw. Returns ``(x+, P+, nu, nis,
    iterations, converged, ok, R+)``; in the full chart the quaternion of ``x+`` is renormalized. ``R+ (B, n, n)``:
    a square root of ``P+ = R+^T R+``: ``R+ = J U``, the rows of ``P+``'s upper Cholesky factor ``U`` in
    reverse order (``A`` is factorized in reverse order, so it comes with ``P+``: the ``W`` of
    ``_posterior_covariance_rev``); NaN at ``[b, n - 1, 0]`` (``U[0, 0]``) where it is not given
    (``ok`` False; the centered coordinates, whose factor is not triangular).

    ``x_true``: the true states ``(B, nx)``, or ``(0, nx)``. Given, each posterior's NEES are evaluated as soon as it is
    formed, with ``P+`` and ``R+`` still in cache (``consistency._nees_one``, the per-trial body of
    ``consistency.nees_batch(x+, P+, x_true, attitude, R+)``: the same numbers): ``nees (B, 9 + 2 N_AXES)``, the 8
    NEES and ``pd`` (1.0 or 0.0), NaN where not evaluated (no truth given, or ``ok`` False), then in the aligned
    chart the per-axis errors ``eps`` and their variances (``N_AXES`` each, unscaled: those of
    ``axes.axis_errors_batch``, bit for bit, from the blocks its block NEES form; NaN in the other charts, whose
    variances are ``P``'s own entries, and where not evaluated); and ``R+`` is not returned
    (``(0, n, n)``): the NEES were its only reader. (One array: each array a kernel
    returns costs its boxing at every call, which a single trial's step pays in full.)
    """
    B, nx = x.shape
    n = P.shape[1]  # the filter's coordinates: the full state, or the error state
    m = y.shape[1]
    xo = np.empty((B, nx))
    Po = np.empty((B, n, n))
    # P+ = Ro^T Ro, Ro = J U+ (Ro[b, n - 1, 0] NaN: not given); returned without the truth only (judged, the NEES
    # read each trial's from Rs, kept in cache: nothing else reads it, and a (B, n, n) array written for nothing is
    # 1.8 MB of memory traffic per step at 250 trials of case B)
    judged = x_true.shape[0] == B
    Ro = np.empty((0 if judged else B, n, n))
    Rs = np.empty((n, n))
    nu = np.empty((B, m))
    nis = np.empty(B)
    its = np.zeros(B, np.int64)
    conv = np.zeros(B, np.bool_)
    ok = np.ones(B, np.bool_)
    hx = np.empty(m)
    Hval = np.zeros((m, NNZ))
    Hdummy = np.zeros((m, NNZ))
    Laug = np.empty((n + (VEC if chart == CHART_ALIGNED else 0), n))  # L, then the rows of the virtual columns (_with_virtual)
    big = n > LARGE_N  # P- factorized by _cholesky_t (the large-n factorization); A by _whiten_information
    Hw = np.empty((0 if big else m, n))  # _whiten's rows (not formed past LARGE_N)
    n_ws, n_wi = scratch_sizes(n, Laug.shape[0] - n) if big else (0, 0)
    ws = np.empty(n_ws)  # _whiten_information's scratch
    wi = np.empty(n_wi, np.int64)
    # whether A's upper triangle is read (the iterations' A z, the Mahalanobis stopping rule's, the copy a step control
    # keeps): not in an EKF step, whose large-n whitening then leaves it unwritten (_whiten_information)
    upper = max_iter > 1 or control != CONTROL_NONE or (tol > 0.0 and stopping == STOP_MAHALANOBIS)
    cen = chart == CHART_ALIGNED and n > LARGE_N  # whitened in the centered point coordinates (above)
    Np = _e_n_points(n)
    g2 = np.empty(n)  # _sqrt_mul's scratch
    Hc = np.zeros((m, NNZ) if cen else (0, NNZ))
    cc = np.zeros((m, NNZ) if cen else (0, NNZ), np.int64)
    rw = np.empty(m)
    A = np.empty((n, n))
    Afin = np.empty((n, n))
    LA = np.empty((n, n))
    Ad = np.empty((n, n) if control == CONTROL_LM else (0, 0))  # Levenberg-Marquardt's damped A + lam I
    rws = np.empty(m)
    z = np.zeros(n)
    zn = np.empty(n)
    zt = np.empty(n)
    d = np.empty(n)
    g = np.empty(n)
    xt = np.empty(nx)
    dx = np.empty(n)
    e = np.empty(n)
    T = np.empty((n, n))
    D = np.empty((3, 3))
    dD = np.empty((4, 3, 3))
    ev = np.full((B, 9 + 2 * N_AXES), np.nan)  # the posteriors' NEES, pd and per-axis errors and variances
    outs = (xo, Po, nu, nis, its, conv, ok, Ro, ev)
    # The loop works on borrowed arrays (``_refs.borrow``: no atomic reference counting in its views and calls). Their owners: the caller's arguments, ``outs`` (returned) and ``own`` (kept to the end).
    own = (Rs, hx, Hval, Hdummy, Laug, Hw, ws, g2, Hc, cc, wi, rw, A, Afin, LA, Ad, rws, z, zn, zt, d, g, xt, dx, e, T,
           D, dD)  # fmt: skip
    x, P, y, R, mask, alpha, cols, x_true = borrow((x, P, y, R, mask, alpha, cols, x_true))
    model = borrow(model)  # (its array, vis, borrowed; its scalars as they are)
    xo, Po, nu, nis, its, conv, ok, Ro, ev = borrow(outs)
    Rs, hx, Hval, Hdummy, Laug, Hw, ws, g2, Hc, cc, wi, rw, A, Afin, LA, Ad, rws, z, zn, zt, d, g, xt, dx, e, T, D, \
        dD = borrow(own)  # fmt: skip
    L = Laug[:n]
    if judged:  # (only then: its views cost time to make and release, which a single trial's step would pay)
        nws = _nees_scratch(nx, n)  # (the owner, kept to the end: _nees_one reads its borrowed arrays, nwb)
        nwb = borrow(nws)  # (its arrays unborrowed would cost _nees_one's calls hundreds of atomic counts per trial)
        wf = (nwb.Tm, nwb.e, nwb.W5, nwb.eps, nwb.C, nwb.Lb, nwb.w, nwb.D, nwb.Dt, nwb.R, nwb.dq, nwb.tmp,
              nwb.v3)  # _one_full's scratch, the arguments of _nees_given after out
    for b in range(B):
        xp = x[b]
        yb = y[b]
        mk = mask[b]
        Rb = Rs if judged else Ro[b]
        Rb[n - 1, 0] = np.nan  # no factor of P+ (yet): set below where the update gives it
        same = b > 0  # R^-1/2: the last trial's where R is the same (a filter's R, the same for every trial)
        if same:
            for r in range(m):
                if R[b, r] != R[b - 1, r]:
                    same = False
                    break
        if not same:
            for r in range(m):
                rws[r] = 1.0 / math.sqrt(R[b, r])
        if cen:
            _center_cov(P[b], L, T, Np)  # T P T^T, factorized in place from its upper triangle
            if not _cholesky_tu(L):
                ok[b] = False
                continue
            _centered_virtual_rows(Laug, Np)
        else:
            if not (_cholesky_t(P[b], L, False) if big else _cholesky(P[b], L)):
                ok[b] = False
                continue
            _with_virtual(chart, Laug)
        for i in range(n):
            e[i] = 0.0
        _measure_at(chart, xp, e, model, alpha[b], True, hx, Hval, xt, D, dD)
        _linearization(hx, Hval, cols, yb, mk, rws, Laug, Hw, rw, A, g, ws, wi, upper, cen, Hc, cc, Np)
        for r in range(m):
            nu[b, r] = yb[r] - hx[r]
        # NIS by Woodbury: |rw|^2 - g^T A^-1 g, g = Hw^T rw
        if not _factor(A, LA):
            ok[b] = False
            continue
        c0 = 0.0
        for r in range(m):
            c0 += rw[r] * rw[r]
        for i in range(n):
            d[i] = g[i]
        _solve(LA, d)
        nis[b] = c0 - _dot(g, d, 0, n)
        cost = c0
        for i in range(n):
            z[i] = 0.0
        if control != CONTROL_NONE:  # (plain Gauss-Newton steps are always taken: LA stays the factor of the last A, fresh)
            _keep_linearization(A, Afin)
        failed = False
        fresh = True
        lam = 1e-3  # Levenberg-Marquardt's damping, per trial
        for it in range(max_iter):
            # z_GN = A^-1 Hw^T (rw + Hw z) = A^-1 (g + (A - I) z); from the prior (z = 0) that is d = A^-1 g of
            # the NIS above. Levenberg-Marquardt: ((1 + lam) I + Hw^T Hw) z = Hw^T (rw + Hw z_j) + lam z_j, i.e.
            # (A + lam I) z = g + (A - I) z_j + lam z_j, kept if the MAP cost does not increase (lam / 10), else x 10
            if it == 0 and control != CONTROL_LM:
                for i in range(n):
                    zn[i] = d[i]
            else:
                _row_products(A, z, zt)  # (zt: free until the line search)
                for i in range(n):
                    zn[i] = (g[i] - z[i]) + zt[i]
                M = A
                if control == CONTROL_LM:
                    for i in range(n):
                        zn[i] += lam * z[i]
                        for j in range(i + 1):
                            Ad[i, j] = A[i, j]
                        Ad[i, i] += lam
                    M = Ad
                if not _factor(M, LA):
                    failed = True
                    break
                _solve(LA, zn)
            fresh = True  # LA is the factor of this iterate's A
            accepted = True
            c_new = cost
            have_jac = False  # hx, Hval already hold h and H at the accepted iterate
            if control == CONTROL_LINE_SEARCH:  # backtracking line search on the MAP cost
                for i in range(n):
                    d[i] = zn[i] - z[i]
                # The full step's Mahalanobis size, known before its cost: if the full step is taken it will not
                # stop the iterations, so its cost evaluation computes H too, which the next linearization needs
                # (h and H at the same point: the same numbers as measuring again there).
                jac_full = False
                if stopping == STOP_MAHALANOBIS and it < max_iter - 1:
                    _row_products(A, d, dx)  # (dx: free until the stopping test)
                    sf = 0.0
                    for i in range(n):
                        sf += d[i] * dx[i]
                    jac_full = not (math.sqrt(max(sf, 0.0)) < tol)
                a = 1.0
                accepted = False
                for _h in range(max_halvings + 1):
                    for i in range(n):
                        zt[i] = z[i] + a * d[i]
                    jac = jac_full and _h == 0
                    ct = _cost_at(chart, zt, xp, L, yb, rws, mk, model, alpha[b], e, xt, hx, Hval if jac else Hdummy,
                                  D, dD, jac, cen, Np, g2)  # fmt: skip
                    if math.isfinite(ct) and ct <= cost:
                        accepted = True
                        have_jac = jac
                        c_new = ct
                        for i in range(n):
                            zn[i] = zt[i]
                        break
                    a *= 0.5
                if not accepted:
                    for i in range(n):
                        zn[i] = z[i]
            elif control == CONTROL_LM:  # Levenberg-Marquardt: the damped step, kept if the MAP cost does not increase
                fresh = False  # LA is the factor of A + lam I
                ct = _cost_at(chart, zn, xp, L, yb, rws, mk, model, alpha[b], e, xt, hx, Hdummy, D, dD, False, cen, Np,
                              g2)  # fmt: skip
                accepted = math.isfinite(ct) and ct <= cost
                if accepted:
                    c_new = ct
                    lam = lam / 10.0
                else:
                    for i in range(n):
                        zn[i] = z[i]
                    lam = lam * 10.0
            its[b] += 1
            # size of the increment dz = zn - z (with tol = 0, the EKF's one step, none is small: not computed)
            size = 0.0
            if tol <= 0.0:
                pass
            elif stopping == STOP_MAHALANOBIS:  # |dz|^2 + |Hw dz|^2 = dz^T A dz
                for i in range(n):
                    dx[i] = zn[i] - z[i]
                _row_products(A, dx, zt)  # (zt: free after the step control)
                for i in range(n):
                    size += dx[i] * zt[i]
                size = math.sqrt(max(size, 0.0))
            elif stopping == STOP_PRIOR:
                for i in range(n):
                    size += (zn[i] - z[i]) ** 2
                size = math.sqrt(size)
            else:
                for i in range(n):
                    zt[i] = zn[i] - z[i]
                _sqrt_mul(L, zt, dx, cen, Np, g2)  # the step in the filter's coordinates
                if stopping == STOP_SCALED:
                    for i in range(n):
                        size = max(size, abs(dx[i]) / math.sqrt(P[b, i, i]))
                else:
                    for i in range(n):
                        size += dx[i] * dx[i]
                    size = math.sqrt(size)
            small = accepted and size < tol
            if not accepted:
                fresh = False  # Afin is an earlier iterate's: factorize it again below
            elif control != CONTROL_NONE:  # the buffers swapped, not copied: A is linearized again before it is read
                A, Afin = Afin, A
            for i in range(n):
                z[i] = zn[i]
            cost = c_new
            if small:
                conv[b] = True
            if small or (control == CONTROL_LINE_SEARCH and not accepted) or it == max_iter - 1:
                break
            if not have_jac:
                _sqrt_mul(L, z, e, cen, Np, g2)
                _measure_at(chart, xp, e, model, alpha[b], True, hx, Hval, xt, D, dD)
            _linearization(hx, Hval, cols, yb, mk, rws, Laug, Hw, rw, A, g, ws, wi, upper, cen, Hc, cc, Np)
        if failed or not (fresh or _factor(Afin, LA)):
            ok[b] = False
            continue
        _sqrt_mul(L, z, e, cen, Np, g2)
        _reset(chart, xp, e, xo[b], D, dD)  # (D, dD: free after the last measurement)
        # P+ = L A^-1 L^T = M M^T, M = L LA^-T: the Joseph form (I - K H) P- (I - K H)^T + K R K^T
        # of kalman.iekf_update with its optimal gain K = L A^-1 Hw^T R^-1/2 at the same H
        if cen:  # P+ = T^-1 (L' A^-1 L'^T) T^-T (its factor T^-1 M' is not triangular: none returned; judged, the
            # NEES take M' itself, the centred covariance's root, in Rb: centred=True below)
            _posterior_covariance_rev(L, LA, A, Rb if judged else T)
            _uncenter_cov(A, Po[b], T, Np)
        else:
            _posterior_covariance_rev(L, LA, Po[b], Rb)  # its W = (M J)^T is P+'s square root J M^T
        if judged:
            st = -1
            if chart == CHART_FULL:  # the full state: _one_full's scratch only (wf), not the 33-array NeesScratch
                st = _nees_given(xo[b], Po[b], x_true[b], Rb, ev[b, :8], *wf)
            if st < 0:
                st = 1 if _nees_one(xo[b], Po[b], x_true[b], attitude, Rb, True, ev[b, :8], nwb, cen) else 0
                if st == 1 and chart == CHART_ALIGNED:  # the per-axis errors and variances its block NEES formed
                    for r in range(N_AXES):
                        ev[b, 9 + r] = nwb.eps[_axis_row(r, n)]
                        ev[b, 9 + N_AXES + r] = nwb.ax[r]
            ev[b, 8] = float(st)
    if judged:
        keep(nws)
    keep(own)
    return outs
