"""Stereo image coordinates and their velocities: geometry by hand, velocities by finite differences in time."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stereopose_mc.core import camera, dynamics, state as st
from stereopose_mc.core import quaternion as qt
from stereopose_mc.core.orbit import Orbit

ORBIT = Orbit(a=8000e3, e=0.15, i=0.5, nu0=0.3)
POINTS = np.array([[1.5, 0.0, 0.0], [0.0, 1.5, 0.0], [0.0, 0.0, 1.5], [-1.06, -1.06, 0.0], [0.3, -0.5, 0.9]])


def _state(omega_scale: float = 0.05) -> np.ndarray:
    """A target 10 m ahead, off-axis, tumbling at ~9 deg/s so the image moves fast."""
    q = qt.normalize(np.array([0.8, 0.3, -0.4, 0.2]))
    k = st.k_from_inertia(np.array([1.0, 1.6, 2.2]))
    omega = omega_scale * np.array([1.0, -2.0, 1.5])
    return st.assemble([1.5, 10.0, -0.8], [0.05, -0.1, 0.03], omega, q, POINTS, k)


def test_positions_match_pinhole_geometry():
    """u_R = x/y, v_R = z/y, u_L = (x - b)/y, v_L = z/y, d = -b/y, with rho_i = rho_0 + R(q) P_i (scipy)."""
    x = _state()
    b, f = 0.7, 2.5
    rho_i = x[st.RHO] + Rotation.from_quat(x[st.QUAT], scalar_first=True).apply(POINTS)
    X, Y, Z = rho_i.T
    y = camera.h_features(x, b, disparity=True, focal=f)
    assert y.shape == (len(POINTS), 9) and camera.channels(True)[-1] == "d"
    np.testing.assert_allclose(y[:, 0], f * X / Y, rtol=1e-14)
    np.testing.assert_allclose(y[:, 1], f * Z / Y, rtol=1e-14)
    np.testing.assert_allclose(y[:, 2], f * (X - b) / Y, rtol=1e-14)
    np.testing.assert_allclose(y[:, 3], f * Z / Y, rtol=1e-14)
    np.testing.assert_allclose(y[:, 8], -f * b / Y, rtol=1e-13)
    np.testing.assert_allclose(y[:, 8], y[:, 2] - y[:, 0], rtol=1e-13)


@pytest.mark.parametrize("disparity", [False, True])
@pytest.mark.parametrize("focal", [1.0, 2.5])
@pytest.mark.parametrize("t0", [0.0, 30.0])
def test_image_velocities_are_time_derivatives(disparity, focal, t0):
    """Velocity channels = central difference (h = 1e-3 s) of the position channels along the dynamics.

    The states at t0 +- h come from ``dynamics.propagate`` (RK4, 4 substeps), so the check covers the
    motion of the points (rho_0' and the rotation w x D P_i), not just the quotient rule.
    """
    b, h = 0.7, 1e-3
    x = _state()
    if t0 > 0.0:
        x = dynamics.propagate(x, 0.0, t0, ORBIT, substeps=60)
    x_minus = dynamics.propagate(x, t0, -h, ORBIT, substeps=4)
    x_plus = dynamics.propagate(x, t0, h, ORBIT, substeps=4)
    y = camera.h_features(np.stack([x_minus, x, x_plus]), b, disparity, focal)
    assert y.shape == (3, len(POINTS), 9 if disparity else 8)
    assert camera.visible(x).all()
    fd = (y[2, :, :4] - y[0, :, :4]) / (2.0 * h)
    vel = y[1, :, 4:8]
    assert np.abs(vel).max() > 1e-2 * focal  # the image does move
    np.testing.assert_allclose(vel, fd, rtol=0, atol=1e-9 * focal)
    # the left and right cameras share v (same height) but not u (the baseline) - per-camera checks
    np.testing.assert_array_equal(vel[:, 1], vel[:, 3])
    assert np.abs(vel[:, 0] - vel[:, 2]).max() > 1e-6 * focal
    if disparity:  # d = -f b / y: its derivative is f b y' / y^2, consistent with du_L - du_R
        d_fd = (y[2, :, 8] - y[0, :, 8]) / (2.0 * h)
        np.testing.assert_allclose(vel[:, 2] - vel[:, 0], d_fd, rtol=0, atol=1e-9 * focal)


def test_focal_length_scales_every_channel():
    x = _state()
    np.testing.assert_allclose(
        camera.h_features(x, 0.7, True, focal=3.0), 3.0 * camera.h_features(x, 0.7, True, focal=1.0), rtol=1e-15
    )


def test_visibility_requires_positive_depth():
    """A point at y < 0 or y = 0 (in or behind the image plane) is not visible; y > 0 is."""
    pts = np.array([[0.0, -3.0, 0.0], [0.0, -1.0, 0.0], [0.0, 1.5, 1.0], [5.0, -0.999, 2.0]])
    x = st.assemble([0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], pts, [0.0, 0.0])
    np.testing.assert_array_equal(camera.visible(x), [False, False, True, True])
    # a rotation by 180 deg about z flips which points are in front
    x_rot = x.copy()
    x_rot[st.QUAT] = [0.0, 0.0, 0.0, 1.0]
    np.testing.assert_array_equal(camera.visible(x_rot), [True, True, False, True])
    both = camera.visible(np.stack([x, x_rot]))
    assert both.shape == (2, len(pts))


def test_channel_counts_are_the_layouts():
    """``core.layout``'s channel counts (what the kernels and the measurement vector use) match the channel names."""
    from stereopose_mc.core import layout

    for disparity in (False, True):
        assert layout.n_channels(disparity) == len(camera.channels(disparity))
        assert layout.n_measurements(4, disparity, True) == 4 * len(camera.channels(disparity)) + layout.PSEUDO_ROWS


@pytest.mark.parametrize("sigma_w_deg", [1.0, 0.2])
def test_flow_second_order_variance_matches_sampled_linearization_error(sigma_w_deg):
    """Draw omega and feature-point errors (independent), evaluate the image velocities' exact change minus the
    Jacobian's prediction: the sampled variance of that remainder is what the formula gives (the rest of the
    second-order terms, point-point through the projection, are a few % of it at 0.2 deg/s)."""
    from stereopose_mc.core.camera import flow_second_order_variance, h_features
    from stereopose_mc.core.jacobians import H_features

    rng = np.random.default_rng(11)
    q = qt.normalize(np.array([0.9, 0.2, -0.3, 0.25]))
    pts = np.array([[1.5, 0.0, 0.0], [0.0, 1.5, 0.3], [-1.0, -1.0, 0.5]])
    x = st.assemble([10.0, 60.0, 10.0], [0.01, -0.02, -0.01], np.radians([-1.5, -1.0, 0.5]), q, pts, np.zeros(2))
    N = pts.shape[0]
    A = rng.normal(size=(3, 3))
    P_ww = (A @ A.T + np.eye(3)) / 3 * np.radians(sigma_w_deg) ** 2
    Bp = rng.normal(size=(N, 3, 3))
    P_pp = (Bp @ np.swapaxes(Bp, -1, -2) + np.eye(3)) / 3 * 0.5
    n_draw = 200_000
    dw = rng.multivariate_normal(np.zeros(3), P_ww, size=n_draw)
    dp = np.stack([rng.multivariate_normal(np.zeros(3), P_pp[i], size=n_draw) for i in range(N)], axis=1)
    xs = np.broadcast_to(x, (n_draw, x.size)).copy()
    xs[:, st.OMEGA] += dw
    ps = st.points_slice(N)
    xs[:, ps] += dp.reshape(n_draw, -1)
    b = 1.0
    H = H_features(x[None], b)[0]  # (N, 8, n)
    lin = np.einsum("icn,bn->bic", H, xs - x)
    rem = h_features(xs, b) - h_features(x[None], b) - lin
    got = flow_second_order_variance(x, P_ww, P_pp, b)
    np.testing.assert_allclose(rem.var(axis=0)[:, 4:], got[:, 4:], rtol=0.05)
    np.testing.assert_array_equal(got[:, :4], 0.0)
    # batched: each trial its own, the same bits as alone
    xb = np.stack([x, x + 0.01])
    both = flow_second_order_variance(xb, np.stack([P_ww, 2 * P_ww]), np.stack([P_pp, P_pp]), b)
    np.testing.assert_array_equal(both[0], flow_second_order_variance(x[None], P_ww[None], P_pp[None], b)[0])
