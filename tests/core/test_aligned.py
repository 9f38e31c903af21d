"""The aligned error state (core/aligned.py): inverse chart, analytic Jacobians, exact symmetries, hand values."""

import numpy as np
import pytest

from stereopose_mc.core import aligned as al, camera, errorstate as es, quaternion as qt, state as st

from scenarios import random_states  # noqa: E402

RNG = np.random.default_rng(11)


def random_state(B=4, N=3):
    return random_states(RNG, B, N)


def _fd(f, x, n, h=1e-6):
    cols = []
    for j in range(n):
        d = np.zeros(n)
        d[j] = h
        cols.append((f(x + d) - f(x - d)) / (2 * h))
    return np.stack(cols, -1)


def test_chart_and_local_are_inverse_for_large_errors():
    x = random_state()
    e = 0.5 * RNG.standard_normal((4, x.shape[-1] - 1))
    np.testing.assert_allclose(al.local(x, al.chart(x, e)), e, atol=1e-12)
    # and the other way round, from two unrelated states (q of either sign)
    y = random_state()
    y[1, st.QUAT] *= -1
    np.testing.assert_allclose(al.chart(x, al.local(x, y))[:, :9], y[:, :9], atol=1e-12)
    np.testing.assert_allclose(qt.dcm(al.chart(x, al.local(x, y))[:, st.QUAT]), qt.dcm(y[:, st.QUAT]), atol=1e-12)


def test_hand_values_of_a_body_rotation():
    """delta = [0, 0, 2 tan(pi/8)] is a 45 deg turn of the body frame about its z axis (Gibbs chart)."""
    x = st.assemble(np.array([[1.0, 50.0, 2.0]]), np.array([[0.1, 0.0, 0.0]]), np.array([[0.0, 0.0, 0.01]]),
                    np.array([[1.0, 0.0, 0.0, 0.0]]), np.array([[[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]]),
                    np.array([[0.1, 0.2]]))  # fmt: skip
    e = np.zeros((1, x.shape[-1] - 1))
    e[0, al.DELTA] = [0.0, 0.0, 2 * np.tan(np.pi / 8)]
    y = al.chart(x, e)[0]
    c = np.sqrt(0.5)
    np.testing.assert_allclose(y[st.QUAT], [np.cos(np.pi / 8), 0, 0, np.sin(np.pi / 8)], atol=1e-15)
    np.testing.assert_allclose(y[13:16], [c, -c, 0.0], atol=1e-15)  # R_z(45)^T [1, 0, 0]
    np.testing.assert_allclose(y[16:19], [2 * c, 2 * c, 0.0], atol=1e-15)  # R_z(45)^T [0, 2, 0]
    np.testing.assert_allclose(y[:9], x[0, :9], atol=1e-15)  # centre of mass, its velocity, omega: unchanged
    # a common shift of the points by d = [0, 0, 1] with e_c = 0: rho moves by -D d = [0, 0, -1] (q = 1)
    e = np.zeros((1, x.shape[-1] - 1))
    e[0, 12:18] = [0, 0, 1, 0, 0, 1]
    y = al.chart(x, e)[0]
    np.testing.assert_allclose(y[st.RHO], [1.0, 50.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(y[st.RHO_DOT], [0.1, 0.0, 0.0] - np.cross([0.0, 0.0, 0.01], [0.0, 0.0, 1.0]), atol=1e-15)


def test_chart_jacobian_matches_finite_differences_away_from_zero():
    x = random_state()
    n = x.shape[-1]
    e = 0.3 * RNG.standard_normal((4, n - 1))
    S = al.chart_jacobian(x, e)
    for b in range(4):
        fd = _fd(lambda v: al.chart(x[b], v), e[b], n - 1)
        np.testing.assert_allclose(S[b], fd, atol=1e-8)


def test_error_map_is_the_derivative_of_local_and_inverts_the_chart():
    x = random_state()
    n = x.shape[-1]
    T, S = al.error_map(x), al.chart_jacobian(x)
    np.testing.assert_allclose(T @ S, np.broadcast_to(np.eye(n - 1), (4, n - 1, n - 1)), atol=1e-12)
    np.testing.assert_allclose(np.einsum("bij,bj->bi", T[:, :, st.QUAT], x[:, st.QUAT]), 0.0, atol=1e-14)
    for b in range(4):
        fd = _fd(lambda v: al.local(x[b], v), x[b], n)
        np.testing.assert_allclose(T[b], fd, atol=1e-8)


@pytest.mark.parametrize("size", [1e-3, 0.3, 2.0])
def test_both_symmetries_are_straight_lines_of_exactly_unchanged_images(size):
    """A pure delta (body-frame rotation) and a common e_P (centre-of-mass gauge) change no image, at any size."""
    x = random_state()
    n = x.shape[-1]
    N = st.n_points(n)
    y0 = camera.h_features(x, 1.0)
    rot = np.zeros((4, n - 1))
    rot[:, al.DELTA] = size * RNG.standard_normal((4, 3))
    gauge = np.zeros((4, n - 1))
    gauge[:, 12 : 12 + 3 * N] = np.tile(size * RNG.standard_normal((4, 3)), N)
    for e in (rot, gauge, rot + gauge):
        np.testing.assert_allclose(camera.h_features(al.chart(x, e), 1.0), y0, rtol=0, atol=1e-13)
    # in the attitude chart the same rotation of the body moves the images unless the points follow it
    a = np.zeros((4, n - 1))
    a[:, es.ATT] = rot[:, al.DELTA]
    assert np.abs(camera.h_features(es.chart(x, a), 1.0) - y0).max() > 1e-4 * size
    # and a generic aligned error does change them
    g = size * RNG.standard_normal((4, n - 1))
    assert np.abs(camera.h_features(al.chart(x, g), 1.0) - y0).max() > 1e-4 * size


def test_covariance_maps_to_the_attitude_chart_like_the_errors_do():
    """For small errors eps_attitude = M e_aligned (M = T_att S_al): the mapped covariance is the errors' covariance."""
    x = random_state(1, 2)
    n = x.shape[-1]
    A = RNG.standard_normal((n - 1, n - 1))
    P = A @ A.T / n + 0.1 * np.eye(n - 1)
    e = 1e-6 * RNG.standard_normal((5, n - 1))
    eps = es.local(x, al.chart(x, e))
    M = es.error_map(x)[0] @ al.chart_jacobian(x)[0]
    np.testing.assert_allclose(eps, e @ M.T, rtol=0, atol=1e-4 * np.abs(e).max())  # second order: ~40 |e|^2
    np.testing.assert_allclose(al.to_attitude_chart(x, P[None])[0], M @ P @ M.T, rtol=1e-12)


def test_a_given_attitude_map_gives_the_same_numbers():
    """``from_attitude_chart`` and ``nees_report`` with the caller's ``M = attitude_map(x)`` (the slots' NEES share one
    between the two): exactly what each computes without it; the map is ``T_att S_al``; ``gauge_complement`` is
    cached per size, read-only."""
    x = random_state(3, 4)
    n = x.shape[-1]
    A = RNG.standard_normal((3, n - 1, n - 1))
    P = A @ np.swapaxes(A, -1, -2) / n + 0.1 * np.eye(n - 1)
    xt = al.chart(x, 0.01 * RNG.standard_normal((3, n - 1)))
    M = al.attitude_map(x)
    assert np.array_equal(M, es.error_map(x) @ al.chart_jacobian(x))
    assert np.array_equal(al.from_attitude_chart(x, P, M), al.from_attitude_chart(x, P))
    given, own = al.nees_report(x, P, xt, M), al.nees_report(x, P, xt)
    assert given.keys() == own.keys() and all(np.array_equal(given[k], own[k]) for k in own)
    V = al.gauge_complement(n)
    assert al.gauge_complement(n) is V and not V.flags.writeable
    np.testing.assert_allclose(V.T @ V, np.eye(n - 4), atol=1e-12)
