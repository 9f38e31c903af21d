"""Compiled kernels of the attitude error state (core/kernels/attitude.py) against core.errorstate and finite
differences; its covariance predict (core/kernels/aligned.py, chart 2) against the dense error-state transition."""

from __future__ import annotations

import numpy as np
import pytest

from stereopose_mc.core import camera, errorstate as es, inertia, jacobians, kalman, quaternion as qt, state as st
from stereopose_mc.core.kernels import aligned as ka, attitude as kt, model as km

ND, NDD = 1.1e-3, 2.0e-9
VIS = np.array([0, 2, 3])


def case(B=4, N=4, seed=7, size=0.3):
    """States ~40 m ahead with unit quaternions, and attitude-chart errors ``eps`` of ``size``."""
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
    assert rel(kt.chart_batch(x, e), es.chart(x, e)) < 1e-15
    assert rel(kt.chart_jacobian_batch(x, e), es.chart_jacobian(x, e)) < 1e-14
    assert rel(kt.chart_jacobian_batch(x, 0 * e), es.chart_jacobian(x)) < 1e-14
    q_scaled = x.copy()
    q_scaled[:, st.QUAT] *= 1.7  # T normalizes the reference quaternion, as numpy's attitude_map
    assert rel(kt.error_map_batch(q_scaled), es.error_map(q_scaled)) < 1e-14
    T = kt.error_map_batch(x)
    assert np.allclose(T @ kt.chart_jacobian_batch(x, 0 * e), np.eye(e.shape[-1]), rtol=0, atol=1e-14)
    # hand values: at q_ref = identity, a unit error a = [0.2, 0, 0] is the quaternion [1, 0.1, 0, 0] / |.|
    x1 = x[:1].copy()
    x1[:, st.QUAT] = [1.0, 0.0, 0.0, 0.0]
    e1 = np.zeros((1, e.shape[-1]))
    e1[0, 9] = 0.2
    np.testing.assert_allclose(kt.chart_batch(x1, e1)[0, st.QUAT], np.array([1.0, 0.1, 0.0, 0.0]) / np.sqrt(1.01),
                               rtol=0, atol=1e-16)  # fmt: skip
    np.testing.assert_array_equal(kt.error_map_batch(x1)[0, 9:12, 9:13], [[0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 2]])


def test_local_inverts_the_chart_like_numpy():
    x, e, _ = case()
    xc = kt.chart_batch(x, e)
    np.testing.assert_allclose(kt.local_batch(x, xc), e, rtol=0, atol=1e-14)
    assert rel(kt.local_batch(x, xc), es.local(x, xc)) < 1e-15
    scaled = xc.copy()
    scaled[:, st.QUAT] *= 0.8  # a non-unit quaternion on either side: normalized as numpy's local does
    ref = x.copy()
    ref[:, st.QUAT] *= 1.3
    assert rel(kt.local_batch(ref, scaled), es.local(ref, scaled)) < 1e-15


def test_chart_jacobian_and_error_map_match_finite_differences():
    x, e, _ = case(B=2)
    S = kt.chart_jacobian_batch(x, e)
    T = kt.error_map_batch(x)
    for b in range(2):
        np.testing.assert_allclose(S[b], fd(lambda v: kt.chart_batch(x[b : b + 1], v[None])[0], e[b]), atol=1e-8)
        np.testing.assert_allclose(T[b], fd(lambda v: es.local(x[b], v), x[b]), atol=1e-8)


@pytest.mark.parametrize("disparity,pseudo,focal", [(False, True, 1.0), (True, True, 800.0), (False, False, 1.0)])
def test_measurement_matches_numpy_h_of_the_chart_times_S(disparity, pseudo, focal):
    x, e, alpha = case()
    B, n = x.shape
    hx, Hval = kt.measure_batch(x, e, VIS, 0.7, disparity, focal, pseudo, alpha, ND, NDD, True)
    xc = es.chart(x, e)
    h_np = [camera.h_features(xc, 0.7, disparity, focal)[:, VIS].reshape(B, -1)]
    H_np = [jacobians.H_features(xc, 0.7, disparity, focal)[:, VIS].reshape(B, -1, n)]
    if pseudo:
        h_np.append(inertia.h_pseudo(xc, alpha, ND, NDD))
        H_np.append(jacobians.H_pseudo(xc, alpha, ND, NDD))
    h_np, H_np = np.concatenate(h_np, -1), np.concatenate(H_np, -2) @ es.chart_jacobian(x, e)
    assert np.max(np.abs(hx - h_np) / np.maximum(np.abs(h_np), 1e-300)) < 1e-13
    cols = kt.measurement_columns(n - 1, VIS, 9 if disparity else 8, pseudo)
    H = km.dense(Hval, cols, n - 1)
    scale = np.max(np.abs(H_np), axis=-1, keepdims=True)
    assert np.max(np.abs(H - H_np) / scale) < 1e-13
    h_only, _ = kt.measure_batch(x, e, VIS, 0.7, disparity, focal, pseudo, alpha, ND, NDD, False)
    assert np.array_equal(h_only, hx)


def test_measurement_jacobian_finite_differences():
    x, e, alpha = case(B=1)
    ne = e.shape[-1]

    def h(v):
        return kt.measure_batch(x, v[None], VIS, 0.5, True, 1.0, True, alpha, ND, NDD, False)[0][0]

    _, Hval = kt.measure_batch(x, e, VIS, 0.5, True, 1.0, True, alpha, ND, NDD, True)
    H = km.dense(Hval, kt.measurement_columns(ne, VIS, 9, True), ne)[0]
    num = fd(h, e[0])
    assert np.all(np.abs(H - num) <= 1e-6 * np.max(np.abs(H), axis=1, keepdims=True))
    assert np.abs(H[:, es.ATT]).max() > 0.0  # the images and the pseudo rows see the attitude


@pytest.mark.parametrize("order", [2, 4])
def test_covariance_predict_matches_the_dense_error_state_transition(order):
    x, _, _ = case(B=3, N=4)
    B, n = x.shape
    rng = np.random.default_rng(3)
    Fd = jacobians.F(x, 6.9e6, ND, NDD, 3.986004418e14)
    Phi = kalman.transition_matrix(Fd, 1.0, "taylor", order)
    Tb = km.transition_reduced_batch(km.F_reduced_batch(x, 6.9e6, ND, NDD, 3.986004418e14), 1.0, order)
    x_pred = x.copy()
    x_pred[:, :13] += 1e-2 * rng.normal(size=(B, 13))
    x_pred[:, st.QUAT] = qt.normalize(x_pred[:, st.QUAT])
    A = rng.normal(size=(B, n - 1, n - 1))
    P = A @ np.swapaxes(A, -1, -2) + np.eye(n - 1)
    Q = np.abs(rng.normal(size=(B, n)))
    T = es.error_map(x_pred)
    Phi_e = T @ Phi @ es.chart_jacobian(x)
    want = Phi_e @ P @ np.swapaxes(Phi_e, -1, -2) + (T * Q[:, None, :]) @ np.swapaxes(T, -1, -2)
    got = ka.predict_covariance_batch(x, x_pred, Tb, P, Q, 2)
    assert rel(got, want) < 1e-12
    assert np.array_equal(got, np.swapaxes(got, -1, -2))
    # the chart argument matters: the aligned chart's P- from the same matrix is another one
    assert rel(ka.predict_covariance_batch(x, x_pred, Tb, P, Q, 1), want) > 1e-3
