"""Quaternion algebra, scalar first, Hamilton convention.

A quaternion is an array ``q[..., 4] = [q0, q1, q2, q3]`` with the scalar ``q0`` first.
``D(q)`` is the rotation matrix that takes target-frame components to leader-frame
components, ``v^L = D(q) v^T``; it equals scipy's
``Rotation.from_quat(q, scalar_first=True).as_matrix()``.
The kinematics are ``q_dot = 1/2 q (x) [0, w_T]`` with ``w_T`` the body-frame rate.
Every function takes any number of leading batch axes (``...``) and keeps them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def normalize(q: Array) -> Array:
    """Unit quaternion ``q / |q|`` (``...,4``)."""
    q = np.asarray(q, dtype=float)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def multiply(p: Array, q: Array) -> Array:
    """Hamilton product ``p (x) q`` (``...,4``)."""
    p0, p1, p2, p3 = np.moveaxis(np.asarray(p, dtype=float), -1, 0)
    q0, q1, q2, q3 = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack(
        [
            p0 * q0 - p1 * q1 - p2 * q2 - p3 * q3,
            p0 * q1 + p1 * q0 + p2 * q3 - p3 * q2,
            p0 * q2 - p1 * q3 + p2 * q0 + p3 * q1,
            p0 * q3 + p1 * q2 - p2 * q1 + p3 * q0,
        ],
        axis=-1,
    )


def conjugate(q: Array) -> Array:
    """Conjugate ``[q0, -q1, -q2, -q3]``; the inverse of a unit quaternion."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def inverse(q: Array) -> Array:
    """Inverse ``q* / |q|^2`` (any non-zero quaternion)."""
    q = np.asarray(q, dtype=float)
    return conjugate(q) / np.sum(q * q, axis=-1, keepdims=True)


def dcm(q: Array) -> Array:
    """Rotation matrix ``D(q)`` (``...,3,3``) of the normalized quaternion.

    Written in the homogeneous form ``D = (...)/|q|^2`` so that a quaternion that has
    drifted off the unit sphere still gives an orthonormal matrix (docs/model.md: q is
    normalized inside D(q)).
    """
    q = np.asarray(q, dtype=float)
    q0, q1, q2, q3 = np.moveaxis(q, -1, 0)
    n2 = q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3
    D = np.empty(q.shape[:-1] + (3, 3))
    D[..., 0, 0] = q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3
    D[..., 0, 1] = 2.0 * (q1 * q2 - q0 * q3)
    D[..., 0, 2] = 2.0 * (q1 * q3 + q0 * q2)
    D[..., 1, 0] = 2.0 * (q1 * q2 + q0 * q3)
    D[..., 1, 1] = q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3
    D[..., 1, 2] = 2.0 * (q2 * q3 - q0 * q1)
    D[..., 2, 0] = 2.0 * (q1 * q3 - q0 * q2)
    D[..., 2, 1] = 2.0 * (q2 * q3 + q0 * q1)
    D[..., 2, 2] = q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3
    return D / n2[..., None, None]


def omega_matrix(q: Array) -> Array:
    """``Q(q)`` (``...,4,3``) such that ``q (x) [0, v] = Q(q) v`` (thesis p. 42)."""
    q = np.asarray(q, dtype=float)
    q0, q1, q2, q3 = np.moveaxis(q, -1, 0)
    Q = np.empty(q.shape[:-1] + (4, 3))
    Q[..., 0, :] = np.stack([-q1, -q2, -q3], axis=-1)
    Q[..., 1, :] = np.stack([q0, -q3, q2], axis=-1)
    Q[..., 2, :] = np.stack([q3, q0, -q1], axis=-1)
    Q[..., 3, :] = np.stack([-q2, q1, q0], axis=-1)
    return Q


def cross(a: Array, b: Array) -> Array:
    """``a x b`` over the last axis, broadcasting (cheaper than ``np.cross`` on small stacks)."""
    a1, a2, a3 = a[..., 0], a[..., 1], a[..., 2]
    b1, b2, b3 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a2 * b3 - a3 * b2, a3 * b1 - a1 * b3, a1 * b2 - a2 * b1], axis=-1)


def matvec(M: Array, v: Array) -> Array:
    """``M v`` over the last axes (``M (...,i,j)``, ``v (...,j)``)."""
    return (M @ v[..., None])[..., 0]


def rmatvec(M: Array, v: Array) -> Array:
    """``M^T v`` over the last axes."""
    return (v[..., None, :] @ M)[..., 0, :]


def skew(v: Array) -> Array:
    """Cross-product matrix ``[v x]`` (``...,3,3``): ``skew(a) @ b == cross(a, b)``."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    x, y, w = np.moveaxis(v, -1, 0)
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)],
        axis=-2,
    )


def error_angle(q_true: Array, q_est: Array) -> Array:
    """Attitude error ``2 acos(|q_e,0|)`` with ``q_e = q (x) q_est^-1`` (rad, ``...``).

    Computed as ``2 atan2(|vec(q_e)|, |q_e,0|)``, which is accurate near zero where
    ``acos`` loses half the digits; both quaternions are normalized first.
    """
    qe = multiply(normalize(q_true), conjugate(normalize(q_est)))
    return 2.0 * np.arctan2(np.linalg.norm(qe[..., 1:], axis=-1), np.abs(qe[..., 0]))


def from_axis_angle(axis: Array, angle: Array) -> Array:
    """Quaternion of a rotation by ``angle`` (rad) about the unit ``axis`` (``...,3``)."""
    axis = np.asarray(axis, dtype=float)
    half = 0.5 * np.asarray(angle, dtype=float)[..., None]
    return np.concatenate([np.cos(half), np.sin(half) * axis], axis=-1)
