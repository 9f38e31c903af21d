"""Compiled kernels of the aligned error state (core/kernels/aligned.py) against core.aligned and finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from stereopose_mc.core import aligned as al, camera, inertia, jacobians, kalman, quaternion as qt, state as st
from stereopose_mc.core.kernels import aligned as ka, model as km

ND, NDD = 1.1e-3, 2.0e-9
VIS = np.array([0, 1, 3, 4])


def case(B=4, N=5, seed=5, size=0.3):
    """States ~40 m ahead with unit quaternions, and aligned errors ``e`` of ``size``."""
    rng = np.random.default_rng(seed)
    x = st.assemble(rng.normal(size=(B, 3)) + [2.0, 40.0, -1.0], 1e-2 * rng.normal(size=(B, 3)),
                    2e-2 * rng.normal(size=(B, 3)), qt.normalize(rng.normal(size=(B, 4))),
                    1.5 * rng.normal(size=(B, N, 3)), 0.2 * rng.normal(size=(B, 2)))  # fmt: skip
    return x, size * rng.normal(size=(B, x.shape[-1] - 1)), 1e-5 * rng.normal(size=(B, 3))


def rel(a, b):
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


def fd(f, v, h=1e-6):
    cols = []
    for j in range(v.size):
        d = np.zeros(v.size)
        d[j] = h
        cols.append((f(v + d) - f(v - d)) / (2 * h))
    return np.stack(cols, -1)


def test_chart_jacobian_and_error_map_match_numpy():
    x, e, _ = case()
    assert rel(ka.chart_batch(x, e), al.chart(x, e)) < 1e-14
    assert rel(ka.chart_jacobian_batch(x, e), al.chart_jacobian(x, e)) < 1e-12
    assert rel(ka.chart_jacobian_batch(x, 0 * e), al.chart_jacobian(x)) < 1e-12
    T = ka.error_map_batch(x)
    assert rel(T, al.error_map(x)) < 1e-12
    ne = e.shape[-1]
    assert np.allclose(T @ ka.chart_jacobian_batch(x, 0 * e), np.eye(ne), rtol=0, atol=1e-12)


def test_local_inverts_the_chart_like_numpy():
    x, e, _ = case()
    xc = ka.chart_batch(x, e)
    np.testing.assert_allclose(ka.local_batch(x, xc), e, rtol=0, atol=1e-13)
    assert rel(ka.local_batch(x, xc), al.local(x, xc)) < 1e-14
    other = xc.copy()
    other[:, st.QUAT] *= 0.8  # non-unit quaternions: normalized as numpy's local does
    ref = x.copy()
    ref[:, st.QUAT] *= 1.3
    assert rel(ka.local_batch(ref, other), al.local(ref, other)) < 1e-14


def test_chart_jacobian_and_error_map_match_finite_differences():
    x, e, _ = case(B=2)
    S = ka.chart_jacobian_batch(x, e)
    T = ka.error_map_batch(x)
    for b in range(2):
        np.testing.assert_allclose(S[b], fd(lambda v: ka.chart_batch(x[b : b + 1], v[None])[0], e[b]), atol=1e-8)
        np.testing.assert_allclose(T[b], fd(lambda v: al.local(x[b], v), x[b]), atol=1e-8)


@pytest.mark.parametrize("disparity,pseudo,focal", [(False, True, 1.0), (True, True, 800.0), (False, False, 1.0)])
def test_measurement_matches_numpy_h_of_the_chart_times_S(disparity, pseudo, focal):
    x, e, alpha = case()
    B, n = x.shape
    hx, Hval = ka.measure_batch(x, e, VIS, 0.7, disparity, focal, pseudo, alpha, ND, NDD, True)
    xc = al.chart(x, e)
    h_np = [camera.h_features(xc, 0.7, disparity, focal)[:, VIS].reshape(B, -1)]
    H_np = [jacobians.H_features(xc, 0.7, disparity, focal)[:, VIS].reshape(B, -1, n)]
    if pseudo:
        h_np.append(inertia.h_pseudo(xc, alpha, ND, NDD))
        H_np.append(jacobians.H_pseudo(xc, alpha, ND, NDD))
    h_np, H_np = np.concatenate(h_np, -1), np.concatenate(H_np, -2) @ al.chart_jacobian(x, e)
    assert np.max(np.abs(hx - h_np) / np.maximum(np.abs(h_np), 1e-300)) < 1e-12
    cols = ka.measurement_columns(n - 1, VIS, 9 if disparity else 8, pseudo)
    H = ka.dense(Hval, cols, n - 1)
    scale = np.max(np.abs(H_np), axis=-1, keepdims=True)  # per row: numpy's H S leaves round-off on delta
    assert np.max(np.abs(H - H_np) / scale) < 1e-12
    h_only, _ = ka.measure_batch(x, e, VIS, 0.7, disparity, focal, pseudo, alpha, ND, NDD, False)
    assert np.array_equal(h_only, hx)


def test_measurement_jacobian_finite_differences_and_no_delta_in_feature_rows():
    x, e, alpha = case(B=1)
    ne = e.shape[-1]

    def h(v):
        return ka.measure_batch(x, v[None], VIS, 0.5, True, 1.0, True, alpha, ND, NDD, False)[0][0]

    _, Hval = ka.measure_batch(x, e, VIS, 0.5, True, 1.0, True, alpha, ND, NDD, True)
    H = ka.dense(Hval, ka.measurement_columns(ne, VIS, 9, True), ne)[0]
    num = fd(h, e[0])
    assert np.all(np.abs(H - num) <= 1e-6 * np.max(np.abs(H), axis=1, keepdims=True))
    assert np.all(H[: 9 * VIS.size, al.DELTA] == 0.0)  # images do not see a rotation of the body frame
    assert np.abs(H[9 * VIS.size :, al.DELTA]).max() > 0.0  # the pseudo-measurement does


@pytest.mark.parametrize("order", [2, 4])
def test_covariance_predict_matches_the_dense_error_state_transition(order):
    x, _, _ = case(B=3, N=4)
    B, n = x.shape
    rng = np.random.default_rng(2)
    Fd = jacobians.F(x, 6.9e6, ND, NDD, 3.986004418e14)
    Phi = kalman.transition_matrix(Fd, 1.0, "taylor", order)
    Tb = km.transition_reduced_batch(km.F_reduced_batch(x, 6.9e6, ND, NDD, 3.986004418e14), 1.0, order)
    x_pred = x.copy()
    x_pred[:, :13] += 1e-2 * rng.normal(size=(B, 13))  # any other state: T is taken there
    x_pred[:, st.QUAT] = qt.normalize(x_pred[:, st.QUAT])
    A = rng.normal(size=(B, n - 1, n - 1))
    P = A @ np.swapaxes(A, -1, -2) + np.eye(n - 1)
    Q = np.abs(rng.normal(size=(B, n)))
    Phi_e = al.error_map(x_pred) @ Phi @ al.chart_jacobian(x)
    T = al.error_map(x_pred)
    want = Phi_e @ P @ np.swapaxes(Phi_e, -1, -2) + (T * Q[:, None, :]) @ np.swapaxes(T, -1, -2)
    got = ka.predict_covariance_batch(x, x_pred, Tb, P, Q, 1)
    assert rel(got, want) < 1e-12
    assert np.array_equal(got, np.swapaxes(got, -1, -2))
