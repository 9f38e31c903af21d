"""Feature slots (filters/slots.py): triangulation, birth Jacobians, the birth covariance, the NEES over occupied slots.

References: the camera's own projection (core.camera.project), finite differences, the linear propagation of the
joint covariance written out as one matrix, Monte Carlo sampling, and the NEES of a smaller state built without the
free slots (core.errorstate.nees_all).
"""

from __future__ import annotations

import numpy as np
import pytest

from stereopose_mc.core import aligned, camera
from stereopose_mc.core import errorstate as es
from stereopose_mc.core import layout as lay
from stereopose_mc.core import quaternion as qt
from stereopose_mc.filters import slots

B_M = 1.0  # baseline (m)


def _state(rng, N: int, B: int = 1) -> np.ndarray:
    q = rng.normal(size=(B, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    x = np.concatenate([np.tile([10.0, 60.0, 10.0], (B, 1)), rng.normal(0, 0.02, (B, 3)), rng.normal(0, 0.003, (B, 3)),
                        q, rng.normal(0, 1.0, (B, 3 * N)), np.tile([-0.18, -0.08], (B, 1))], axis=-1)
    return x


def _covariance(rng, ne: int, B: int = 1, scale: float = 1e-2) -> np.ndarray:
    A = rng.normal(size=(B, ne, ne)) * np.sqrt(scale / ne)
    return A @ np.swapaxes(A, -1, -2) + 1e-6 * np.eye(ne)


@pytest.mark.parametrize("focal", [1.0, 1407.0])
def test_triangulate_inverts_the_projection(focal):
    p = np.array([[1.3, 58.0, -2.1], [-4.0, 61.5, 3.3]])
    y = camera.project(p, np.zeros_like(p), B_M, False, focal)
    got, _ = slots.triangulate(y, B_M, focal)
    np.testing.assert_allclose(got, p, rtol=1e-12)


@pytest.mark.parametrize("focal", [1.0, 1407.0])
def test_triangulation_jacobian_matches_finite_differences(focal):
    p = np.array([1.3, 58.0, -2.1])
    y = camera.project(p, np.zeros(3), B_M, False, focal).copy()
    y[3] += 3e-4 * focal  # unequal rows: the mean row is used
    _, J = slots.triangulate(y, B_M, focal)
    h = 1e-7 * focal
    fd = np.stack([(slots.triangulate(y + h * e, B_M, focal)[0] - slots.triangulate(y - h * e, B_M, focal)[0]) / (2 * h)
                   for e in np.eye(8)[:4]], axis=-1)
    np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-9 * np.abs(fd).max())


def test_birth_jacobians_match_finite_differences():
    rng = np.random.default_rng(3)
    x = _state(rng, 4)[0]
    p = np.array([1.0, 59.0, -1.5])
    y = camera.project(p, np.zeros(3), B_M)
    p0, J = slots.triangulate(y, B_M)
    Gx, Gy = slots.birth_jacobians(x, p0, J)
    ne = x.size - 1

    def f(eps, dy):
        return slots.birth_point(es.chart(x, eps), slots.triangulate(y + dy, B_M)[0])

    h = 1e-6
    fdx = np.stack([(f(h * e, 0) - f(-h * e, 0)) / (2 * h) for e in np.eye(ne)], axis=-1)
    np.testing.assert_allclose(Gx, fdx, atol=1e-6 * np.abs(fdx).max())
    hy = 1e-9
    fdy = np.stack([(f(np.zeros(ne), hy * e) - f(np.zeros(ne), -hy * e)) / (2 * hy) for e in np.eye(8)[:4]], axis=-1)
    np.testing.assert_allclose(Gy, fdy, rtol=1e-5, atol=1e-6 * np.abs(fdy).max())


def _births(rng, N=4, B=3):
    x = _state(rng, N, B)
    ne = x.shape[1] - 1
    P = _covariance(rng, ne, B)
    born = np.zeros((B, N), bool)
    born[0, 1] = born[1, 1] = born[1, 3] = True
    freed = np.zeros((B, N), bool)
    freed[2, 0] = freed[0, 2] = True
    pts = np.array([[1.0, 59.0, -1.5], [-2.0, 61.0, 0.7], [0.5, 60.2, 2.0], [1.7, 58.1, -0.2]])
    y = np.broadcast_to(camera.project(pts, np.zeros_like(pts), B_M), (B, N, 8)).copy()
    var = np.full(4, 1e-8)
    return x, P, born, freed, y, var


def test_birth_is_the_linear_propagation_of_the_joint_covariance():
    """P+ = A [[P, 0], [0, R]] A^T, A the new error state's Jacobian in [eps_old, dy of every born slot]."""
    x, P, born, freed, y, var = _births(np.random.default_rng(5))
    x2, P2 = slots.manage(x, P, "attitude", born, freed, y, var, B_M)
    B, N = born.shape
    ne = P.shape[-1]
    for b in range(B):
        js = np.flatnonzero(born[b])
        A = np.zeros((ne, ne + 4 * js.size))
        A[:, :ne] = np.eye(ne)
        Paug = np.zeros((ne + 4 * js.size,) * 2)
        Paug[:ne, :ne] = P[b]
        for i, j in enumerate(js):
            ej = slice(lay.e_point(j), lay.e_point(j + 1))
            p, J = slots.triangulate(y[b, j], B_M)
            Gx, Gy = slots.birth_jacobians(x[b], p, J)
            A[ej, :ne] = Gx
            A[ej, ne + 4 * i : ne + 4 * i + 4] = Gy
            Paug[ne + 4 * i : ne + 4 * i + 4, ne + 4 * i : ne + 4 * i + 4] = np.diag(var)
            np.testing.assert_allclose(x2[b, lay.point(j) : lay.point(j + 1)], slots.birth_point(x[b], p), rtol=1e-14)
        ref = A @ Paug @ A.T
        for j in np.flatnonzero(freed[b] & ~born[b]):
            ej = slice(lay.e_point(j), lay.e_point(j + 1))
            ref[ej, :] = ref[:, ej] = 0.0
            ref[ej, ej] = slots.FREED_VARIANCE * np.eye(3)
        np.testing.assert_allclose(P2[b], ref, rtol=1e-10, atol=1e-14)
    untouched = ~(born | freed).any(axis=1)
    assert not untouched.any() or np.array_equal(P2[untouched], P[untouched])


def test_birth_in_the_aligned_chart_is_the_attitude_chart_birth_mapped_back():
    x, P, born, freed, y, var = _births(np.random.default_rng(7))
    xa, Pa = slots.manage(x, P, "aligned", born, freed, y, var, B_M)
    xt, Pt = slots.manage(x, aligned.to_attitude_chart(x, P), "attitude", born, freed, y, var, B_M)
    np.testing.assert_array_equal(xa, xt)
    np.testing.assert_allclose(aligned.to_attitude_chart(xa, Pa), Pt, rtol=1e-8, atol=1e-12)


def test_birth_covariance_covers_the_sampled_errors():
    """Monte Carlo: truths drawn around the estimate, their point measured with noise; the born point's error with
    the pose's error has NEES/dof ~ 1 (chi-square mean) over 4000 draws."""
    rng = np.random.default_rng(11)
    N, M = 2, 4000
    x_hat = _state(rng, N)[0]
    ne = x_hat.size - 1
    # attitude sigma 1 mrad: at 10 mrad the born point's error is ~0.95 correlated with the attitude's, and the
    # joint's thin direction is then the size of the second-order terms (NEES/dof 1.36 here)
    P = np.diag(np.r_[np.full(3, 0.04), np.full(3, 1e-4), np.full(3, 1e-6), np.full(3, 1e-6), np.full(3 * N, 0.25),
                      [0.1, 0.1]])  # fmt: skip
    sig_y = 3e-4  # ~0.4 px at f = 1407 px
    eps = rng.multivariate_normal(np.zeros(ne), P, size=M)
    x_true = es.chart(np.broadcast_to(x_hat, (M, ne + 1)), eps)
    P_body = np.array([0.8, -0.4, 1.1])  # the tracked point, in T
    p_true = x_true[:, 0:3] + qt.matvec(qt.dcm(x_true[:, lay.QUAT : lay.QUAT + 4]), P_body)
    y = camera.project(p_true, np.zeros_like(p_true), B_M) + rng.normal(0, sig_y, (M, 8))
    born = np.zeros((M, N), bool)
    born[:, 1] = True
    xs, Ps = slots.manage(np.broadcast_to(x_hat, (M, ne + 1)), np.broadcast_to(P, (M, ne, ne)), "attitude", born,
                          np.zeros_like(born), np.stack([y, y], axis=1), np.full(4, sig_y**2), B_M)  # fmt: skip
    x_true[:, lay.point(1) : lay.point(2)] = P_body
    e = es.estimation_error(xs, x_true)
    keep = np.r_[0:3, 9:12, lay.e_point(1) : lay.e_point(2)]  # rho, attitude, the born point
    d2 = es.mahalanobis2(e[:, keep], Ps[:, keep][:, :, keep])
    assert abs(d2.mean() / keep.size - 1.0) < 0.06, d2.mean() / keep.size


def test_nees_over_occupied_slots_is_that_of_the_state_without_the_free_ones():
    rng = np.random.default_rng(13)
    N, B = 4, 3
    x_hat = _state(rng, N, B)
    ne = x_hat.shape[1] - 1
    P = _covariance(rng, ne, B)
    x_true = es.chart(x_hat, rng.normal(0, 0.05, (B, ne)))
    occupied = np.ones((B, N), bool)
    occupied[0, 2] = occupied[2, 0] = occupied[2, 3] = False
    x_true[1, lay.point(1) : lay.point(2)] = np.nan  # a track without a known true point: free for the NEES
    occ = occupied & np.isfinite(x_true[:, lay.POINTS : lay.point(N)].reshape(B, N, 3)).all(-1)
    got, dof = slots.nees(x_hat, P, "attitude", x_true, occupied)
    for b in range(B):
        keep_pts = np.flatnonzero(occ[b])
        xi = np.r_[0:lay.POINTS, *(np.arange(lay.point(j), lay.point(j + 1)) for j in keep_pts), x_hat.shape[1] - 2,
                   x_hat.shape[1] - 1]  # fmt: skip
        ei = np.r_[0:lay.E_POINTS, *(np.arange(lay.e_point(j), lay.e_point(j + 1)) for j in keep_pts), ne - 2, ne - 1]
        xr = x_hat[b, xi][None]
        ref = aligned.nees_report(xr, aligned.from_attitude_chart(xr, P[b][np.ix_(ei, ei)][None]), x_true[b, xi][None])
        ref_dof = es.nees_dof(xi.size)
        for k, v in ref.items():
            np.testing.assert_allclose(got[k][b], v[0], rtol=1e-8, err_msg=k)
            assert dof[k][b] == ref_dof[k], k
