"""Analytic Jacobians against Richardson-extrapolated central differences of the models.

The reference is the model itself (``dynamics.f``, ``camera.h_features``,
``inertia.h_pseudo``) differentiated numerically, column by column, with a step scaled
per component. Entries are compared in units of a typical perturbation of each state
component (``A_ij * s_j``, ``s_j`` = the component's scale) so that columns in metres,
rad/s, quaternion units and ``k`` weigh alike; the tolerance is relative to the entry
plus the largest scaled entry of its row.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as hst

from stereopose_mc.core import camera, dynamics, inertia, jacobians
from stereopose_mc.core import quaternion as qt
from stereopose_mc.core import state as st

RTOL = 1e-7  # F (its FD reference is limited by the gravity cancellation); observed <= 3e-9
RTOL_H = 1e-9  # measurement Jacobians; observed <= 2e-11
# floor of the per-component scale, by block (rho, rho_dot, omega, q, points, k)
FLOORS = {"rho": 1.0, "rho_dot": 1e-2, "omega": 1e-3, "q": 0.1, "feature_points": 0.1, "k": 0.1}

BATCH_SHAPES = [(), (3,), (2, 3)]


def component_scale(x: np.ndarray) -> np.ndarray:
    """Per-component scale ``max(|x_j|, floor of its block)`` (..., n)."""
    n = x.shape[-1]
    floor = np.empty(n)
    for name, sl in st.block_index(st.n_points(n)).items():
        floor[sl] = FLOORS[name]
    return np.maximum(np.abs(x), floor)


def fd_jacobian(fun, x: np.ndarray, rel_step=1e-3, scale: np.ndarray | None = None) -> np.ndarray:
    """``d fun / dx`` (out_shape + (n,)) by central differences with one Richardson step.

    ``D(h) = (fun(x + h e_j) - fun(x - h e_j)) / 2h`` and ``(4 D(h/2) - D(h)) / 3``
    (error O(h^4)), with ``h_j = rel_step_j * scale_j`` per batch element (``rel_step``
    a float or one per component; ``scale`` defaults to ``component_scale(x)``).
    """
    n = x.shape[-1]
    h_all = rel_step * (component_scale(x) if scale is None else scale)
    f0 = fun(x)
    out = np.empty(f0.shape + (n,))
    extra = f0.ndim - (x.ndim - 1)  # trailing output axes after the batch axes
    for j in range(n):

        def central(h):
            xp = x.copy()
            xm = x.copy()
            xp[..., j] += h
            xm[..., j] -= h
            return (fun(xp) - fun(xm)) / (2.0 * h.reshape(h.shape + (1,) * extra))

        h = h_all[..., j]
        out[..., j] = (4.0 * central(0.5 * h) - central(h)) / 3.0
    return out


def assert_jacobian_close(A: np.ndarray, A_fd: np.ndarray, x: np.ndarray, rtol: float = RTOL) -> float:
    """``|A - A_fd| <= rtol (|A_fd| + max_row |A_fd|)`` in scaled units; returns worst ratio."""
    assert A.shape == A_fd.shape
    s = component_scale(x)
    s = s.reshape(s.shape[:-1] + (1,) * (A.ndim - x.ndim) + s.shape[-1:])
    a, b = A * s, A_fd * s
    row = np.max(np.abs(b), axis=-1, keepdims=True)
    err = np.abs(a - b)
    bound = rtol * (np.abs(b) + row)
    zero = bound == 0.0
    assert np.all(err[zero] == 0.0), "non-zero analytic entry where the model's row is exactly flat"
    ratio = float(np.max(err[~zero] / bound[~zero], initial=0.0))
    assert ratio <= 1.0, f"worst error / tolerance = {ratio:.3g}"
    return ratio


def random_state(rng: np.random.Generator, shape: tuple[int, ...], N: int) -> np.ndarray:
    """State with features in front of the cameras, non-unit q (|q| in 0.5..2)."""
    rho = np.stack(
        [rng.uniform(-20, 20, shape), rng.uniform(20, 80, shape), rng.uniform(-20, 20, shape)], axis=-1
    )
    rho_dot = rng.uniform(-0.1, 0.1, shape + (3,))
    omega = np.deg2rad(rng.uniform(-2.0, 2.0, shape + (3,)))
    q = qt.normalize(rng.standard_normal(shape + (4,))) * rng.uniform(0.5, 2.0, shape + (1,))
    u = rng.standard_normal(shape + (N, 3))
    pts = 2.0 * u / np.linalg.norm(u, axis=-1, keepdims=True) * rng.uniform(0, 1, shape + (N, 1)) ** (1 / 3)
    k = rng.uniform(-2.0, 2.0, shape + (2,))
    return st.assemble(rho, rho_dot, omega, q, pts, k)


def leader_values(rng: np.random.Generator, shape: tuple[int, ...], batched: bool):
    """Realistic ``(r_L, nu_dot, nu_ddot)``, scalars or one per batch element."""
    sz = shape if batched else None
    r_L = rng.uniform(6.8e6, 7.5e6, sz)
    nu_dot = rng.uniform(0.9e-3, 1.2e-3, sz)
    nu_ddot = rng.uniform(-1e-7, 1e-7, sz)
    return r_L, nu_dot, nu_ddot


cases = hst.fixed_dictionaries(
    {
        "seed": hst.integers(0, 2**32 - 1),
        "shape": hst.sampled_from(BATCH_SHAPES),
        "N": hst.integers(1, 5),
        "batched_leader": hst.booleans(),
    }
)


@settings(max_examples=25, deadline=None)
@given(case=cases)
def test_F_matches_finite_differences(case):
    rng = np.random.default_rng(case["seed"])
    x = random_state(rng, case["shape"], case["N"])
    r_L, nd, ndd = leader_values(rng, case["shape"], case["batched_leader"])
    A = jacobians.F(x, r_L, nd, ndd)
    n = x.shape[-1]
    assert A.shape == case["shape"] + (n, n)
    # f's x-row holds two ~8 m/s^2 gravity terms that cancel: long rho and rho_dot steps
    # keep its round-off (eps * 8 / h) far below the tolerance (f is linear in rho_dot and
    # gravity varies on the r_L scale, so the truncation error stays negligible).
    steps = np.full(n, 1e-3)
    steps[st.RHO] = 1e-1
    steps[st.RHO_DOT] = 1.0
    A_fd = fd_jacobian(lambda z: dynamics.f(z, r_L, nd, ndd), x, rel_step=steps)
    assert_jacobian_close(A, A_fd, x)
    # feature-point and k rows of f are identically zero
    assert np.all(A[..., st.POINTS0 :, :] == 0.0)


@settings(max_examples=25, deadline=None)
@given(
    case=cases,
    disparity=hst.booleans(),
    focal=hst.sampled_from([1.0, 0.7, 1200.0]),
    baseline=hst.floats(0.1, 2.0),
)
def test_H_features_matches_finite_differences(case, disparity, focal, baseline):
    rng = np.random.default_rng(case["seed"])
    x = random_state(rng, case["shape"], case["N"])
    H = jacobians.H_features(x, baseline, disparity, focal)
    C = 9 if disparity else 8
    assert H.shape == case["shape"] + (case["N"], C, x.shape[-1])
    H_fd = fd_jacobian(lambda z: camera.h_features(z, baseline, disparity, focal), x)
    assert_jacobian_close(H, H_fd, x, RTOL_H)


@settings(max_examples=25, deadline=None)
@given(case=cases)
def test_H_pseudo_matches_finite_differences(case):
    rng = np.random.default_rng(case["seed"])
    x = random_state(rng, case["shape"], case["N"])
    _, nd, ndd = leader_values(rng, case["shape"], case["batched_leader"])
    alpha = rng.normal(0.0, 1e-4, case["shape"] + (3,))
    H = jacobians.H_pseudo(x, alpha, nd, ndd)
    assert H.shape == case["shape"] + (3, x.shape[-1])
    H_fd = fd_jacobian(lambda z: inertia.h_pseudo(z, alpha, nd, ndd), x)
    assert_jacobian_close(H, H_fd, x, RTOL_H)
    # only omega, q and k enter the pseudo-measurement
    N = case["N"]
    assert np.all(H[..., : st.OMEGA.start] == 0.0)
    assert np.all(H[..., st.points_slice(N)] == 0.0)


@settings(max_examples=20, deadline=None)
@given(seed=hst.integers(0, 2**32 - 1), shape=hst.sampled_from(BATCH_SHAPES))
def test_dcm_derivative_matches_finite_differences(seed, shape):
    rng = np.random.default_rng(seed)
    q = rng.standard_normal(shape + (4,)) * rng.uniform(0.5, 2.0, shape + (1,))
    D, dD = jacobians.dcm_derivative(q)
    np.testing.assert_allclose(D, qt.dcm(q), rtol=0, atol=1e-15)
    dD_fd = np.moveaxis(fd_jacobian(qt.dcm, q, scale=np.maximum(np.abs(q), 0.1)), -1, -3)
    # |dD/dq| ~ 1/|q|: compare in units of a relative change of q
    qn = np.linalg.norm(q, axis=-1)[..., None, None, None]
    np.testing.assert_allclose(dD * qn, dD_fd * qn, rtol=0, atol=1e-9)
    # D is homogeneous of degree 0 in q: Euler's relation sum_j q_j dD/dq_j = 0
    np.testing.assert_allclose(np.einsum("...j,...jab->...ab", q, dD), 0.0, atol=1e-14)


@settings(max_examples=20, deadline=None)
@given(case=cases)
def test_F_along_q_follows_homogeneity(case):
    """f_omega is of degree 0 in q, f_q of degree 1 (Q(q) linear, D scale-free): Euler's relation."""
    rng = np.random.default_rng(case["seed"])
    x = random_state(rng, case["shape"], case["N"])
    r_L, nd, ndd = leader_values(rng, case["shape"], case["batched_leader"])
    A = jacobians.F(x, r_L, nd, ndd)
    q = x[..., st.QUAT]
    fx = dynamics.f(x, r_L, nd, ndd)
    along_q = np.einsum("...ij,...j->...i", A[..., :, st.QUAT], q)
    assert np.max(np.abs(along_q[..., st.OMEGA])) <= 1e-12 * np.max(np.abs(A[..., st.OMEGA, st.QUAT]))
    np.testing.assert_allclose(along_q[..., st.QUAT], fx[..., st.QUAT], rtol=1e-10, atol=1e-18)
    # the feature measurement and the pseudo-measurement depend on q only through D(q)
    Hf = jacobians.H_features(x, 0.5, True, 1.0)
    hf_q = np.einsum("...ij,...j->...i", Hf[..., st.QUAT], q[..., None, :])
    assert np.max(np.abs(hf_q)) <= 1e-12 * np.max(np.abs(Hf[..., st.QUAT]))
    Hp = jacobians.H_pseudo(x, rng.normal(0, 1e-4, case["shape"] + (3,)), nd, ndd)
    hp_q = np.einsum("...ij,...j->...i", Hp[..., st.QUAT], q)
    assert np.max(np.abs(hp_q)) <= 1e-12 * np.max(np.abs(Hp[..., st.QUAT]))


@settings(max_examples=20, deadline=None)
@given(case=cases, disparity=hst.booleans(), focal=hst.sampled_from([1.0, 3.0]))
def test_H_features_dense_equals_compact_and_is_block_sparse(case, disparity, focal):
    rng = np.random.default_rng(case["seed"])
    x = random_state(rng, case["shape"], case["N"])
    N, n = case["N"], x.shape[-1]
    shared, own = jacobians.H_features_compact(x, 0.4, disparity, focal)
    C = 9 if disparity else 8
    assert shared.shape == case["shape"] + (N, C, 13)
    assert own.shape == case["shape"] + (N, C, 3)
    H = jacobians.H_features(x, 0.4, disparity, focal)
    np.testing.assert_array_equal(H[..., :13], shared)
    ks = st.k_slice(N)
    assert np.all(H[..., ks] == 0.0)
    for i in range(N):
        c0 = st.POINTS0 + 3 * i
        np.testing.assert_array_equal(H[..., i, :, c0 : c0 + 3], own[..., i, :, :])
        others = np.ones(n, bool)
        others[:13] = False
        others[c0 : c0 + 3] = False
        assert np.all(H[..., i, :, others] == 0.0)
    # the own block is not trivially zero (features do depend on their point)
    assert np.all(np.abs(own[..., :4, :]).max(axis=(-2, -1)) > 0.0)


def test_F_translation_block_hand_values():
    """Circular leader, target at the origin: the CW/HCW matrix (gravity gradient diag(2, -1, -1) n^2)."""
    mu = 3.986004418e14
    r = 7.0e6
    n_ = np.sqrt(mu / r**3)
    x = st.assemble(np.zeros(3), np.zeros(3), np.zeros(3), [1.0, 0, 0, 0], np.zeros((1, 3)), np.zeros(2))
    A = jacobians.F(x, r, n_, 0.0, mu)
    expected = np.array([[3 * n_**2, 0, 0], [0, 0, 0], [0, 0, -(n_**2)]])
    np.testing.assert_allclose(A[3:6, 0:3], expected, rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(A[3:6, 3:6], [[0, 2 * n_, 0], [-2 * n_, 0, 0], [0, 0, 0]], rtol=1e-15)
    np.testing.assert_array_equal(A[0:3, 3:6], np.eye(3))
