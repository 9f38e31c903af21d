"""Compiled kernels of the two error-state charts against their numpy twins and finite differences.

The aligned chart (core/kernels/aligned.py against core.aligned) and the attitude chart
(core/kernels/attitude.py against core.errorstate), through their batch entry points
(core/kernels/charts.py, the chart's code as an argument): ``x [+] e`` and its inverse,
``S = dx/de`` at any ``e``, ``T = de/dx``, the row-sparse ``H_e = H S`` with ``h(x [+] e)``,
and the error-state covariance predict ``Phi_e P Phi_e^T + T Q T^T``
(``aligned.predict_covariance_batch`` with the chart's code); what only one chart has, at
the end.
"""

from __future__ import annotations

import numpy as np
import pytest

from stereopose_mc.core import aligned as al, camera, errorstate as es, inertia, jacobians, kalman
from stereopose_mc.core import quaternion as qt, state as st
from stereopose_mc.core.kernels import aligned as ka, charts as kch, model as km

ND, NDD = 1.1e-3, 2.0e-9
VIS = np.array([0, 1, 3, 4])
CHARTS = {"aligned": (1, al), "attitude": (2, es)}  # chart name: (the kernels' chart code, the numpy twin)


def case(B=4, N=5, seed=5, size=0.3):
    """States ~40 m ahead with unit quaternions, and errors ``e`` of ``size``."""
    rng = np.random.default_rng(seed)
    x = st.assemble(rng.normal(size=(B, 3)) + [2.0, 40.0, -1.0], 1e-2 * rng.normal(size=(B, 3)),
                    2e-2 * rng.normal(size=(B, 3)), qt.normalize(rng.normal(size=(B, 4))),
                    1.5 * rng.normal(size=(B, N, 3)), 0.2 * rng.normal(size=(B, 2)))  # fmt: skip
    return x, size * rng.normal(size=(B, x.shape[-1] - 1)), 1e-5 * rng.normal(size=(B, 3))


def rel(a, b):
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


def fd(f, v, h=1e-6):
    """Central differences of ``f`` at ``v``, one column per component."""
    cols = []
    for j in range(v.size):
        d = np.zeros(v.size)
        d[j] = h
        cols.append((f(v + d) - f(v - d)) / (2 * h))
    return np.stack(cols, -1)


@pytest.mark.parametrize("name", CHARTS)
def test_chart_jacobian_and_error_map_match_numpy(name):
    code, ref = CHARTS[name]
    x, e, _ = case()
    assert rel(kch.chart_batch(code, x, e), ref.chart(x, e)) < 1e-14
    assert rel(kch.chart_jacobian_batch(code, x, e), ref.chart_jacobian(x, e)) < 1e-12
    assert rel(kch.chart_jacobian_batch(code, x, 0 * e), ref.chart_jacobian(x)) < 1e-12
    T = kch.error_map_batch(code, x)
    assert rel(T, ref.error_map(x)) < 1e-12
    scaled = x.copy()
    scaled[:, st.QUAT] *= 1.7  # T normalizes the reference quaternion, as numpy does
    assert rel(kch.error_map_batch(code, scaled), ref.error_map(scaled)) < 1e-12
    assert np.allclose(T @ kch.chart_jacobian_batch(code, x, 0 * e), np.eye(e.shape[-1]), rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", CHARTS)
def test_local_inverts_the_chart_like_numpy(name):
    code, ref = CHARTS[name]
    x, e, _ = case()
    xc = kch.chart_batch(code, x, e)
    np.testing.assert_allclose(kch.local_batch(code, x, xc), e, rtol=0, atol=1e-13)
    assert rel(kch.local_batch(code, x, xc), ref.local(x, xc)) < 1e-14
    other = xc.copy()
    other[:, st.QUAT] *= 0.8  # non-unit quaternions on either side: normalized as numpy's local does
    x_ref = x.copy()
    x_ref[:, st.QUAT] *= 1.3
    assert rel(kch.local_batch(code, x_ref, other), ref.local(x_ref, other)) < 1e-14


@pytest.mark.parametrize("name", CHARTS)
def test_chart_jacobian_and_error_map_match_finite_differences(name):
    code, ref = CHARTS[name]
    x, e, _ = case(B=2)
    S = kch.chart_jacobian_batch(code, x, e)
    T = kch.error_map_batch(code, x)
    for b in range(2):
        np.testing.assert_allclose(S[b], fd(lambda v: kch.chart_batch(code, x[b : b + 1], v[None])[0], e[b]), atol=1e-8)
        np.testing.assert_allclose(T[b], fd(lambda v: ref.local(x[b], v), x[b]), atol=1e-8)


@pytest.mark.parametrize("name", CHARTS)
@pytest.mark.parametrize("disparity,pseudo,focal", [(False, True, 1.0), (True, True, 800.0), (False, False, 1.0)])
def test_measurement_matches_numpy_h_of_the_chart_times_S(name, disparity, pseudo, focal):
    code, ref = CHARTS[name]
    x, e, alpha = case()
    B, n = x.shape
    hx, Hval = kch.measure_batch(code, x, e, km.StepModel(VIS, 0.7, disparity, focal, pseudo, ND, NDD), alpha, True)
    xc = ref.chart(x, e)
    h_np = [camera.h_features(xc, 0.7, disparity, focal)[:, VIS].reshape(B, -1)]
    H_np = [jacobians.H_features(xc, 0.7, disparity, focal)[:, VIS].reshape(B, -1, n)]
    if pseudo:
        h_np.append(inertia.h_pseudo(xc, alpha, ND, NDD))
        H_np.append(jacobians.H_pseudo(xc, alpha, ND, NDD))
    h_np, H_np = np.concatenate(h_np, -1), np.concatenate(H_np, -2) @ ref.chart_jacobian(x, e)
    assert np.max(np.abs(hx - h_np) / np.maximum(np.abs(h_np), 1e-300)) < 1e-12
    H = kch.dense(code, Hval, kch.measurement_columns(code, n - 1, VIS, 9 if disparity else 8, pseudo), n - 1)
    scale = np.max(np.abs(H_np), axis=-1, keepdims=True)  # per row: numpy's H S leaves round-off on delta
    assert np.max(np.abs(H - H_np) / scale) < 1e-12
    model = km.StepModel(VIS, 0.7, disparity, focal, pseudo, ND, NDD)
    h_only, _ = kch.measure_batch(code, x, e, model, alpha, False)
    assert np.array_equal(h_only, hx)


@pytest.mark.parametrize("name", CHARTS)
def test_measurement_jacobian_finite_differences(name):
    code, _ = CHARTS[name]
    x, e, alpha = case(B=1)
    ne = e.shape[-1]

    def h(v):
        model = km.StepModel(VIS, 0.5, True, 1.0, True, ND, NDD)
        return kch.measure_batch(code, x, v[None], model, alpha, False)[0][0]

    _, Hval = kch.measure_batch(code, x, e, km.StepModel(VIS, 0.5, True, 1.0, True, ND, NDD), alpha, True)
    H = kch.dense(code, Hval, kch.measurement_columns(code, ne, VIS, 9, True), ne)[0]
    assert np.all(np.abs(H - fd(h, e[0])) <= 1e-6 * np.max(np.abs(H), axis=1, keepdims=True))


@pytest.mark.parametrize("name", CHARTS)
@pytest.mark.parametrize("order", [2, 4])
@pytest.mark.parametrize("N", [4, 20])  # BLAS products; past 64 columns from the non-zeros of Phi_e's rows
def test_covariance_predict_matches_the_dense_error_state_transition(name, order, N):
    code, ref = CHARTS[name]
    x, _, _ = case(B=3, N=N)
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
    T = ref.error_map(x_pred)
    Phi_e = T @ Phi @ ref.chart_jacobian(x)
    want = Phi_e @ P @ np.swapaxes(Phi_e, -1, -2) + (T * Q[:, None, :]) @ np.swapaxes(T, -1, -2)
    got = ka.predict_covariance_batch(x, x_pred, Tb, P, Q, code)
    assert rel(got, want) < 1e-12
    assert np.array_equal(got, np.swapaxes(got, -1, -2))
    other = ka.predict_covariance_batch(x, x_pred, Tb, P, Q, 3 - code)
    assert rel(other, want) > 1e-3  # the chart argument matters: the other chart's P- is another matrix


# --- what only one chart has ---------------------------------------------------------


def test_aligned_feature_rows_do_not_see_a_rotation_of_the_body_frame():
    """``H_e`` of the aligned chart: zero (not round-off) on ``delta`` in the image rows; the pseudo rows see it."""
    x, e, alpha = case(B=1)
    ne = e.shape[-1]
    _, Hval = kch.measure_batch(1, x, e, km.StepModel(VIS, 0.5, True, 1.0, True, ND, NDD), alpha, True)
    H = kch.dense(1, Hval, kch.measurement_columns(1, ne, VIS, 9, True), ne)[0]
    assert np.all(H[: 9 * VIS.size, al.DELTA] == 0.0)
    assert np.abs(H[9 * VIS.size :, al.DELTA]).max() > 0.0


def test_attitude_chart_hand_values():
    """At ``q_ref`` = identity: ``a = [0.2, 0, 0]`` is the quaternion ``[1, 0.1, 0, 0] / |.|``, ``Xi = [0 | 2 I]``;
    the attitude columns of ``H_e`` are those the images and the pseudo rows see."""
    x, e, alpha = case(B=1)
    x[:, st.QUAT] = [1.0, 0.0, 0.0, 0.0]
    a = np.zeros((1, e.shape[-1]))
    a[0, 9] = 0.2
    np.testing.assert_allclose(kch.chart_batch(2, x, a)[0, st.QUAT], np.array([1.0, 0.1, 0.0, 0.0]) / np.sqrt(1.01),
                               rtol=0, atol=1e-16)  # fmt: skip
    np.testing.assert_array_equal(kch.error_map_batch(2, x)[0, 9:12, 9:13], [[0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 2]])
    _, Hval = kch.measure_batch(2, x, e, km.StepModel(VIS, 0.5, True, 1.0, True, ND, NDD), alpha, True)
    H = kch.dense(2, Hval, kch.measurement_columns(2, e.shape[-1], VIS, 9, True), e.shape[-1])[0]
    assert np.abs(H[: 9 * VIS.size, es.ATT]).max() > 0.0 and np.abs(H[9 * VIS.size :, es.ATT]).max() > 0.0
