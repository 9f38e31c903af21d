"""Quaternion algebra (scalar-first Hamilton) against scipy and algebraic identities."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as hs
from scipy.spatial.transform import Rotation

from stereopose_mc.core import quaternion as qt

finite = dict(allow_nan=False, allow_infinity=False)
quat = hs.lists(hs.floats(-1.0, 1.0, **finite), min_size=4, max_size=4).map(np.array).filter(
    lambda v: np.linalg.norm(v) > 0.1
)
vec3 = hs.lists(hs.floats(-2.0, 2.0, **finite), min_size=3, max_size=3).map(np.array)
scale = hs.floats(1e-3, 1e3)
SETTINGS = settings(max_examples=150, deadline=None)


@SETTINGS
@given(q=quat)
def test_dcm_is_a_rotation(q):
    D = qt.dcm(q)
    np.testing.assert_allclose(D @ D.T, np.eye(3), atol=1e-14)
    assert abs(np.linalg.det(D) - 1.0) < 1e-14


@SETTINGS
@given(q=quat, c=scale)
def test_dcm_sign_and_scale_invariant(q, c):
    """D(q) = D(-q) = D(c q) = D(q / |q|): the norm is divided out inside D."""
    D = qt.dcm(q)
    np.testing.assert_allclose(qt.dcm(-q), D, atol=1e-15)
    np.testing.assert_allclose(qt.dcm(c * q), D, atol=1e-14)
    np.testing.assert_allclose(qt.dcm(qt.normalize(q)), D, atol=1e-14)


@SETTINGS
@given(q=quat)
def test_dcm_matches_scipy(q):
    """``D(q)`` equals scipy's matrix of the same scalar-first quaternion (``v^L = D v^T``)."""
    np.testing.assert_allclose(qt.dcm(q), Rotation.from_quat(q, scalar_first=True).as_matrix(), atol=1e-14)


@SETTINGS
@given(p=quat, q=quat)
def test_multiply_matches_composition(p, q):
    """D(p (x) q) = D(p) D(q); the product equals scipy's composition; |p q| = |p| |q|."""
    pq = qt.multiply(p, q)
    np.testing.assert_allclose(qt.dcm(pq), qt.dcm(p) @ qt.dcm(q), atol=1e-14)
    assert abs(np.linalg.norm(pq) - np.linalg.norm(p) * np.linalg.norm(q)) < 1e-14
    ref = (Rotation.from_quat(p, scalar_first=True) * Rotation.from_quat(q, scalar_first=True)).as_quat(
        scalar_first=True
    )
    u = qt.normalize(pq)
    np.testing.assert_allclose(u * np.sign(u @ ref), ref, atol=1e-14)


@SETTINGS
@given(p=quat, q=quat)
def test_inverse_round_trips(p, q):
    identity = np.array([1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(qt.multiply(q, qt.inverse(q)), identity, atol=1e-14)
    np.testing.assert_allclose(qt.multiply(qt.inverse(q), q), identity, atol=1e-14)
    np.testing.assert_allclose(qt.multiply(qt.multiply(p, q), qt.inverse(q)), p, atol=1e-13)
    np.testing.assert_allclose(qt.multiply(qt.inverse(p), qt.multiply(p, q)), q, atol=1e-13)
    u = qt.normalize(q)
    np.testing.assert_allclose(qt.conjugate(u), qt.inverse(u), atol=1e-15)
    np.testing.assert_allclose(qt.dcm(qt.inverse(q)), qt.dcm(q).T, atol=1e-14)


@SETTINGS
@given(p=quat, q=quat)
def test_error_angle_matches_scipy(p, q):
    """``error_angle`` equals the magnitude of ``R1^-1 R2`` (and does not depend on signs or norms)."""
    ref = (Rotation.from_quat(p, scalar_first=True).inv() * Rotation.from_quat(q, scalar_first=True)).magnitude()
    got = qt.error_angle(p, q)
    assert abs(got - ref) < 1e-7 if ref > 3.14 else abs(got - ref) < 1e-12
    assert abs(qt.error_angle(-3.0 * p, 0.5 * q) - got) < 1e-12
    assert 0.0 <= got <= np.pi


@SETTINGS
@given(q=quat, axis=vec3, log_angle=hs.floats(-10.0, -1.0))
def test_error_angle_small_angles(q, axis, log_angle):
    """A known small rotation (down to 1e-10 rad) is recovered to ~1e-15 rad (``2 acos`` would return 0)."""
    if np.linalg.norm(axis) < 1e-3:
        axis = np.array([0.0, 0.0, 1.0])
    angle = 10.0**log_angle
    dq = qt.from_axis_angle(axis / np.linalg.norm(axis), angle)
    np.testing.assert_allclose(qt.error_angle(qt.multiply(dq, q), q), angle, rtol=1e-6, atol=1e-15)
    np.testing.assert_allclose(qt.error_angle(q, qt.multiply(q, dq)), angle, rtol=1e-6, atol=1e-15)


@SETTINGS
@given(axis=vec3, angle=hs.floats(-6.0, 6.0))
def test_from_axis_angle_matches_rotvec(axis, angle):
    if np.linalg.norm(axis) < 1e-3:
        return
    n = axis / np.linalg.norm(axis)
    np.testing.assert_allclose(
        qt.dcm(qt.from_axis_angle(n, angle)), Rotation.from_rotvec(angle * n).as_matrix(), atol=1e-14
    )


@SETTINGS
@given(q=quat, v=vec3)
def test_omega_matrix_is_right_product(q, v):
    """``Q(q) v = q (x) [0, v]``; ``skew(a) b = a x b``."""
    np.testing.assert_allclose(qt.omega_matrix(q) @ v, qt.multiply(q, np.concatenate([[0.0], v])), atol=1e-15)
    np.testing.assert_allclose(qt.skew(v) @ q[:3], np.cross(v, q[:3]), atol=1e-15)


@SETTINGS
@given(q=quat, w=vec3)
def test_kinematics_rotate_dcm_with_omega(q, w):
    """Along ``q' = 1/2 Q(q) D^T w`` the matrix obeys ``D' = [w x] D`` (central difference, h = 1e-6)."""
    q = qt.normalize(q)
    D = qt.dcm(q)
    q_dot = 0.5 * qt.omega_matrix(q) @ (D.T @ w)
    h = 1e-6
    D_dot = (qt.dcm(q + h * q_dot) - qt.dcm(q - h * q_dot)) / (2.0 * h)
    np.testing.assert_allclose(D_dot, qt.skew(w) @ D, atol=1e-8)
    assert abs(q @ q_dot) < 1e-15  # the kinematics keep |q| = 1


def test_batch_shapes_preserved():
    """Every kernel keeps leading axes ``()``, ``(B,)``, ``(B, C)`` and matches the one-at-a-time result."""
    rng = np.random.default_rng(0)
    P, Q_, V = rng.normal(size=(3, 5, 4)), rng.normal(size=(3, 5, 4)), rng.normal(size=(3, 5, 3))
    cases = {
        "normalize": (lambda p, q, v: qt.normalize(p), (4,)),
        "conjugate": (lambda p, q, v: qt.conjugate(p), (4,)),
        "inverse": (lambda p, q, v: qt.inverse(p), (4,)),
        "multiply": (lambda p, q, v: qt.multiply(p, q), (4,)),
        "dcm": (lambda p, q, v: qt.dcm(p), (3, 3)),
        "omega_matrix": (lambda p, q, v: qt.omega_matrix(p), (4, 3)),
        "skew": (lambda p, q, v: qt.skew(v), (3, 3)),
        "error_angle": (lambda p, q, v: qt.error_angle(p, q), ()),
        "from_axis_angle": (lambda p, q, v: qt.from_axis_angle(v, p[..., 0]), (4,)),
    }
    for name, (fn, tail) in cases.items():
        full = np.asarray(fn(P, Q_, V))
        assert full.shape == (3, 5) + tail, name
        assert np.asarray(fn(P[0], Q_[0], V[0])).shape == (5,) + tail, name
        single = np.asarray(fn(P[1, 2], Q_[1, 2], V[1, 2]))
        assert single.shape == tail, name
        np.testing.assert_allclose(single, full[1, 2], rtol=0, atol=1e-15, err_msg=name)
