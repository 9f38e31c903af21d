"""Hermann-Krener rank test of the torque-free rigid body (thesis ch. 4).

References: hand-derived gradient entries, central finite differences of the Lie
derivatives, the Lie derivative as the derivative along the flow of ``f``, direct
integration of Euler's equations (a step along the null space leaves the output
unchanged), and the degenerate motions whose rank follows from the physics.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from stereopose_mc.core import observability as ob


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _scale_direction(inertia):
    return np.concatenate([np.zeros(3), _unit(inertia)])


@st.composite
def generic_states(draw):
    """Rates with every component away from zero, three distinct moments."""
    mags = [draw(st.floats(0.05, 1.0)) for _ in range(3)]
    signs = [draw(st.sampled_from([-1.0, 1.0])) for _ in range(3)]
    scale = draw(st.sampled_from([1e-4, 1e-2, 1.0, 10.0]))  # rad/s
    omega = scale * np.array(mags) * np.array(signs)
    base = np.sort([draw(st.floats(1.0, 3.0)) for _ in range(3)])
    gaps = [draw(st.floats(0.1, 1.0)) for _ in range(2)]
    inertia = np.array([base[0], base[0] + gaps[0], base[0] + gaps[0] + gaps[1]])
    perm = draw(st.permutations([0, 1, 2]))
    inertia = inertia[list(perm)] * draw(st.sampled_from([1e-3, 1.0, 1e3]))
    return omega, inertia


@settings(max_examples=60, deadline=None)
@given(generic_states(), st.sampled_from([1, 2]))
def test_generic_rank_five_null_space_is_inertia_scale(state, order):
    omega, inertia = state
    r = ob.euler_rank_test(omega, inertia, order=order)
    assert r.rank == 5
    assert r.null_space.shape == (6, 1)
    n = r.null_space[:, 0]
    assert n[3] > 0  # sign convention: positive I_x component
    np.testing.assert_allclose(n, _scale_direction(inertia), atol=1e-10)
    # and it is a null vector of the physical O itself
    O = ob.observability_matrix(np.concatenate([omega, inertia]), order)
    assert np.linalg.norm(O @ n) <= 1e-12 * np.linalg.norm(O)


def test_hand_derived_entries_of_grad_L1h():
    # x = [0.3, -0.5, 0.7, 1, 2, 4]:  L1h_x = (I_y - I_z)/I_x w_y w_z,  L1h_y = (I_z - I_x)/I_y w_z w_x
    x = np.array([0.3, -0.5, 0.7, 1.0, 2.0, 4.0])
    g = ob.grad_L1h(x)
    # d L1h_x / d I_x = -(I_y - I_z) w_y w_z / I_x^2 = -(2 - 4)(-0.5)(0.7)/1 = -0.7
    assert g[0, 3] == pytest.approx(-0.7, rel=1e-15)
    # d L1h_x / d I_z = -w_y w_z / I_x = 0.35
    assert g[0, 5] == pytest.approx(0.35, rel=1e-15)
    # d L1h_y / d w_x = (I_z - I_x)/I_y w_z = 1.5 * 0.7 = 1.05
    assert g[1, 0] == pytest.approx(1.05, rel=1e-15)
    # d L1h_y / d I_y = -(I_z - I_x) w_z w_x / I_y^2 = -3 * 0.21 / 4 = -0.1575
    assert g[1, 4] == pytest.approx(-0.1575, rel=1e-14)
    # d L1h_z / d w_z = 0 (w_z' does not depend on w_z)
    assert g[2, 2] == 0.0


def _fd_jacobian(fun, x, h=1e-6):
    cols = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h * max(1.0, abs(x[i]))
        cols.append((fun(x + e) - fun(x - e)) / (2 * e[i]))
    return np.stack(cols, axis=-1)


@settings(max_examples=25, deadline=None)
@given(generic_states())
def test_gradients_match_finite_differences(state):
    omega, inertia = state
    # O(1) units so a fixed FD step is well conditioned
    omega = omega / np.linalg.norm(omega)
    inertia = inertia / inertia.max()
    x = np.concatenate([omega, inertia])
    fd = _fd_jacobian(lambda y: ob.lie_derivatives(y, order=2), x)
    np.testing.assert_allclose(ob.grad_L0h(x), fd[0:3], atol=1e-8)
    np.testing.assert_allclose(ob.grad_L1h(x), fd[3:6], atol=1e-7)
    np.testing.assert_allclose(ob.grad_L2h(x), fd[6:9], atol=1e-7)


@settings(max_examples=25, deadline=None)
@given(generic_states())
def test_lie_derivatives_are_derivatives_along_the_flow(state):
    omega, inertia = state
    omega = omega / np.linalg.norm(omega)
    x = np.concatenate([omega, inertia / inertia.max()])
    L = ob.lie_derivatives(x, order=2)
    f = ob.euler_f(x)
    # L1h = w' (the rate part of f); L2h = d/ds L1h(x + s f) at s = 0 (central difference)
    np.testing.assert_allclose(L[3:6], f[:3], rtol=1e-14, atol=1e-15)
    h = 1e-6
    dL1 = (ob.lie_derivatives(x + h * f)[3:6] - ob.lie_derivatives(x - h * f)[3:6]) / (2 * h)
    np.testing.assert_allclose(L[6:9], dL1, atol=1e-8)
    # torque-free Euler from the cross product form: I_x w_x' = (I_y - I_z) w_y w_z
    I = x[3:]
    assert I[0] * f[0] == pytest.approx((I[1] - I[2]) * x[1] * x[2], rel=1e-12, abs=1e-15)


def test_null_space_direction_leaves_the_output_unchanged():
    """Integrating Euler's equations: I -> (1 + eps) I gives the same w(t); changing I_x alone does not."""
    w0 = np.array([0.3, -0.2, 0.5])
    inertia = np.array([0.83, 1.0, 1.083])

    def traj(I):
        sol = solve_ivp(lambda t, w: ob.euler_f(np.concatenate([w, I]))[:3], (0, 30), w0, rtol=1e-11, atol=1e-13,
                        t_eval=np.linspace(0, 30, 61))  # fmt: skip
        return sol.y

    n = ob.euler_rank_test(w0, inertia).null_space[:, 0]
    base = traj(inertia)
    along = traj(inertia + 0.05 * n[3:])
    across = traj(inertia + 0.05 * np.array([1.0, 0.0, 0.0]))
    assert np.max(np.abs(along - base)) < 1e-9
    assert np.max(np.abs(across - base)) > 1e-3


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("order", [1, 2])
def test_spin_about_a_principal_axis_reveals_nothing_about_inertia(axis, order):
    # steady spin: w stays constant for every inertia, so no inertia direction is observable
    omega = np.zeros(3)
    omega[axis] = 0.4
    r = ob.euler_rank_test(omega, [0.83, 1.0, 1.083], order=order)
    assert r.rank == 3
    N = r.null_space
    assert N.shape == (6, 3)
    np.testing.assert_allclose(N[:3], 0.0, atol=1e-14)
    np.testing.assert_allclose(N.T @ N, np.eye(3), atol=1e-12)


def test_spin_in_a_principal_plane_needs_the_second_lie_derivative():
    # w_z = 0: only w_z' = c_z w_x w_y is non-zero at t = 0, so first order sees one ratio only;
    # the second derivatives of w_x and w_y see the other one.
    omega = [0.3, -0.4, 0.0]
    inertia = [0.83, 1.0, 1.083]
    r1 = ob.euler_rank_test(omega, inertia, order=1)
    r2 = ob.euler_rank_test(omega, inertia, order=2)
    assert r1.rank == 4
    assert r2.rank == 5
    np.testing.assert_allclose(r2.null_space[:, 0], _scale_direction(inertia), atol=1e-10)


def test_no_rotation_rank_three():
    r = ob.euler_rank_test([0.0, 0.0, 0.0], [1.0, 2.0, 2.5])
    assert r.rank == 3
    assert np.all(r.singular_values[3:] == 0.0)


@pytest.mark.parametrize("inertia", [[2.0, 2.0, 2.0], [1.0, 1.0, 1.7], [1.3, 0.9, 1.3]])
def test_spherical_and_axisymmetric_inertia_keep_rank_five(inertia):
    """Degenerate inertia does not lose rank locally: at a sphere w' = 0, but any asymmetric
    perturbation of I makes w vary at once, so the ratios stay (locally) distinguishable;
    only the common scale is unobservable."""
    r = ob.euler_rank_test([0.3, -0.2, 0.5], inertia, order=1)
    assert r.rank == 5
    np.testing.assert_allclose(r.null_space[:, 0], _scale_direction(inertia), atol=1e-10)
    if len(set(inertia)) == 1:
        np.testing.assert_allclose(ob.euler_f(np.r_[[0.3, -0.2, 0.5], inertia])[:3], 0.0, atol=1e-16)


def test_rank_is_unit_free():
    omega = np.deg2rad([-0.1, -0.1, 0.034])  # case B, 1e-3 rad/s
    inertia = np.array([0.83, 1.0, 1.083])
    a = ob.euler_rank_test(omega, inertia)
    b = ob.euler_rank_test(omega * 1e4, inertia * 1e-6)
    assert a.rank == b.rank == 5
    np.testing.assert_allclose(a.scaled_singular_values, b.scaled_singular_values, rtol=1e-8, atol=1e-15)
    # same direction in the I block; the (zero) rate block compared in units of |w| / max I
    np.testing.assert_allclose(_unit(a.null_space[3:, 0]), _unit(b.null_space[3:, 0]), atol=1e-10)
    for r, w, I in ((a, omega, inertia), (b, omega * 1e4, inertia * 1e-6)):
        rate_part = r.null_space[:3, 0] / np.linalg.norm(w)
        inertia_part = r.null_space[3:, 0] / I.max()
        assert np.linalg.norm(rate_part) <= 1e-12 * np.linalg.norm(inertia_part)


def test_batched_matrix_equals_loop():
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.normal(size=(4, 2, 3)), rng.uniform(1, 2, size=(4, 2, 3))], axis=-1)
    for order in (1, 2):
        O = ob.observability_matrix(x, order)
        assert O.shape == (4, 2, 3 * (order + 1), 6)
        for i in range(4):
            for j in range(2):
                np.testing.assert_array_equal(O[i, j], ob.observability_matrix(x[i, j], order))
    assert ob.euler_f(x[0, 0]).shape == (6,)


def test_rank_analysis_maps_null_space_through_column_scaling():
    # O = [[1, -2000]]: null space ∝ [2000, 1]; column scale (1, 1000) makes it O(1)
    r = ob.rank_analysis(np.array([[1.0, -2000.0]]), column_scale=np.array([1.0, 1000.0]))
    assert r.rank == 1
    np.testing.assert_allclose(r.null_space[:, 0], _unit([2000.0, 1.0]), rtol=1e-9)
    # a known rank-2 3x3 matrix
    A = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 6.1], [1.0, 2.0, 3.0]])
    r = ob.rank_analysis(A)
    assert r.rank == 2
    np.testing.assert_allclose(A @ r.null_space, 0.0, atol=1e-12)
    np.testing.assert_allclose(r.null_space[:, 0], _unit([2.0, -1.0, 0.0]), atol=1e-12)  # first component > 0


def test_invalid_inputs():
    with pytest.raises(ValueError):
        ob.euler_rank_test([0.1, 0.2, 0.3], [1.0, 0.0, 2.0])
    with pytest.raises(ValueError):
        ob.observability_matrix(np.ones(6), order=3)
    with pytest.raises(ValueError):
        ob.rank_analysis(np.ones((2, 3, 3)))
    with pytest.raises(ValueError):
        ob.rank_analysis(np.ones((2, 3)), column_scale=np.array([1.0, -1.0, 1.0]))


# --------------------------------------------------------------------------- filter-state Gramian
#
# References: the observability matrix of a constant linear system stacked by matrix powers;
# eigen-pairs constructed by hand; the CRLB by a plain linear solve of the information
# matrix; the invariances of the nonlinear camera model h_features under finite steps.

from scipy.linalg import expm  # noqa: E402

from stereopose_mc.core import camera, jacobians  # noqa: E402
from stereopose_mc.core import quaternion as qt  # noqa: E402
from stereopose_mc.core import state as stt  # noqa: E402


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gramian_of_a_linear_toy_equals_the_stacked_observability_matrix(seed):
    rng = np.random.default_rng(seed)
    n, m, K, dt = 5, 2, 7, 0.3
    F = rng.normal(size=(n, n))
    H = rng.normal(size=(m, n))
    Phi = expm(F * dt)
    sig = rng.uniform(0.5, 2.0, size=(K + 1, m))
    w = 1.0 / sig**2
    w[0] = 0.0  # no measurement at t_0
    w[3, 1] = 0.0  # one row missing at t_3
    # reference: O = [H; H Phi; H Phi^2; ...], W = O^T R^-1 O
    O = np.vstack([H @ np.linalg.matrix_power(Phi, k) for k in range(K + 1)])
    W_ref = O.T @ np.diag(w.reshape(-1)) @ O
    W = ob.observability_gramian(np.broadcast_to(Phi, (K, n, n)), np.broadcast_to(H, (K + 1, m, n)), w)
    np.testing.assert_allclose(W, W_ref, rtol=1e-10, atol=1e-10 * np.abs(W_ref).max())
    # the square root: W = O_w^T O_w
    Ow = ob.whitened_observability_matrix(np.broadcast_to(Phi, (K, n, n)), np.broadcast_to(H, (K + 1, m, n)), w)
    np.testing.assert_allclose(Ow.T @ Ow, W_ref, rtol=1e-10, atol=1e-10 * np.abs(W_ref).max())
    # leading batch axes: two systems at once equal each alone
    F2 = rng.normal(size=(n, n))
    Phis = np.stack([np.broadcast_to(Phi, (K, n, n)), np.broadcast_to(expm(F2 * dt), (K, n, n))])
    Wb = ob.observability_gramian(Phis, np.broadcast_to(H, (2, K + 1, m, n)), np.broadcast_to(w, (2, K + 1, m)))
    assert Wb.shape == (2, n, n)
    np.testing.assert_allclose(Wb[0], W, rtol=1e-12, atol=1e-12 * np.abs(W).max())
    O2 = np.vstack([H @ np.linalg.matrix_power(expm(F2 * dt), k) for k in range(K + 1)])
    W2 = O2.T @ np.diag(w.reshape(-1)) @ O2
    np.testing.assert_allclose(Wb[1], W2, rtol=1e-10, atol=1e-10 * np.abs(W2).max())


def test_gramian_of_a_double_integrator_sees_no_position_from_velocity():
    # x = [p, v], p' = v, y = v: the position is unobservable, W e_p = 0 exactly
    F = np.array([[0.0, 1.0], [0.0, 0.0]])
    Phi = expm(F * 0.5)
    W = ob.observability_gramian(np.broadcast_to(Phi, (4, 2, 2)), np.broadcast_to([[0.0, 1.0]], (5, 1, 2)), np.ones((5, 1)))
    assert W[0, 0] == 0.0 and W[0, 1] == 0.0
    assert W[1, 1] == pytest.approx(5.0)


def test_cumulative_transitions_chain_in_order():
    rng = np.random.default_rng(3)
    A, B = rng.normal(size=(2, 3, 3))
    Phi = ob.cumulative_transitions(np.stack([A, B]))
    np.testing.assert_allclose(Phi[0], np.eye(3))
    np.testing.assert_allclose(Phi[1], A)
    np.testing.assert_allclose(Phi[2], B @ A)  # Phi(t2,t0) = Phi(t2,t1) Phi(t1,t0), not A B


def test_gramian_eigen_projects_out_fixed_directions_in_scaled_coordinates():
    rng = np.random.default_rng(4)
    n = 6
    V, _ = np.linalg.qr(rng.normal(size=(n, n)))  # orthonormal eigenvectors in scaled coordinates
    lam = np.array([0.0, 1e-6, 3e-3, 0.2, 1.0, 5.0])
    s = np.array([1e-3, 2.0, 0.5, 10.0, 1.0, 3e2])  # characteristic sizes
    Ws = V @ np.diag(lam) @ V.T
    W = Ws / s[:, None] / s[None, :]  # physical Gramian: W~ = S W S
    e = ob.gramian_eigen(W, s, fixed=V[:, [0]])
    np.testing.assert_allclose(e.eigenvalues, lam[1:], atol=1e-12 * 5.0)
    for i in range(n - 1):  # eigenvectors: +-V[:, i+1]
        assert abs(abs(e.eigenvectors[:, i] @ V[:, i + 1]) - 1.0) < 1e-9
    assert e.lambda_max == pytest.approx(5.0)
    assert e.fixed_rayleigh[0] == pytest.approx(0.0, abs=1e-12)
    # projecting out an eigenvector with a large eigenvalue removes it from the spectrum
    e2 = ob.gramian_eigen(W, s, fixed=V[:, [5]])
    np.testing.assert_allclose(e2.eigenvalues, lam[:5], atol=1e-12 * 5.0)
    assert e2.fixed_rayleigh[0] == pytest.approx(5.0)
    with pytest.raises(ValueError):
        ob.gramian_eigen(W, s, fixed=2.0 * V[:, [0]])  # not orthonormal


def test_crlb_covariance_is_the_inverse_information():
    rng = np.random.default_rng(5)
    n = 5
    A = rng.normal(size=(8, n)) * np.array([1e3, 1.0, 1e-2, 10.0, 1.0])
    W = A.T @ A
    p = np.array([1.0, 1e-4, 4.0, 1e-2, 0.5])
    J = W + np.diag(1.0 / p)
    C_ref = np.linalg.solve(J, np.eye(n))
    np.testing.assert_allclose(ob.crlb_covariance(W, p), C_ref, rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(ob.crlb_sigma(W, p), np.sqrt(np.diag(C_ref)), rtol=1e-8)
    mask = np.array([False, False, False, True, True])
    J2 = W + np.diag(np.where(mask, 0.0, 1.0 / p))
    np.testing.assert_allclose(ob.crlb_covariance(W, p, mask), np.linalg.solve(J2, np.eye(n)), rtol=1e-7, atol=1e-14)
    # no measurements: the prior
    np.testing.assert_allclose(ob.crlb_sigma(np.zeros((n, n)), p), np.sqrt(p), rtol=1e-14)


def _random_filter_state(rng, n_points=4):
    q = qt.normalize(rng.normal(size=4))
    P = rng.normal(size=(n_points, 3))
    return stt.assemble(
        [rng.uniform(-5, 5), rng.uniform(40, 80), rng.uniform(-5, 5)],
        rng.normal(scale=0.05, size=3),
        rng.normal(scale=0.02, size=3),
        q,
        P,
        rng.normal(scale=0.2, size=2),
    )


@pytest.mark.parametrize("seed", [0, 1])
def test_structural_directions_leave_the_images_unchanged(seed):
    rng = np.random.default_rng(seed)
    x = _random_filter_state(rng)
    b = 1.0

    def h(xx):
        return camera.h_features(xx, b).reshape(-1)

    Hx = jacobians.H_features(x, b).reshape(-1, x.size)
    # quaternion norm: exactly invariant (D(q) is normalized), also for a finite step
    for eps in (1e-3, 0.5):
        np.testing.assert_allclose(h(x + eps * ob.quaternion_norm_direction(x)), h(x), rtol=1e-13, atol=1e-15)
    assert np.abs(Hx @ ob.quaternion_norm_direction(x)).max() < 1e-14 * np.abs(Hx).max()
    # gauge and centre-of-mass shift: first-order invariant, the change of h is O(eps^2)
    for dirs in (ob.gauge_directions(x), ob.com_shift_directions(x)):
        assert dirs.shape == (x.size, 3)
        assert np.abs(Hx @ dirs).max() < 1e-12 * np.abs(Hx).max()
        for j in range(3):
            d = dirs[:, j] / np.linalg.norm(dirs[:, j])
            d1 = np.abs(h(x + 1e-3 * d) - h(x)).max()
            d2 = np.abs(h(x + 0.5e-3 * d) - h(x)).max()
            assert d1 < 1e-3 * 1e-3 * np.abs(Hx).max() * 10  # far below a first-order change
            assert d2 == pytest.approx(d1 / 4.0, rel=0.05)  # quadratic
    # a generic direction changes h at first order
    d = rng.normal(size=x.size)
    d /= np.linalg.norm(d)
    assert np.abs(h(x + 1e-3 * d) - h(x)).max() > 1e-3 * 1e-3


def test_structural_directions_are_batched():
    rng = np.random.default_rng(9)
    xs = np.stack([_random_filter_state(rng) for _ in range(3)])
    for fn in (ob.gauge_directions, ob.com_shift_directions):
        out = fn(xs)
        assert out.shape == xs.shape + (3,)
        np.testing.assert_allclose(out[1], fn(xs[1]), rtol=1e-15, atol=1e-15)
    assert ob.quaternion_norm_direction(xs).shape == xs.shape


def test_filter_state_names_and_description():
    names = ob.filter_state_names(2)
    assert len(names) == stt.size(2) == 21
    assert names[:3] == ("rho_x", "rho_y", "rho_z") and names[9:13] == ("q0", "q1", "q2", "q3")
    assert names[13:19] == ("P1_x", "P1_y", "P1_z", "P2_x", "P2_y", "P2_z") and names[-2:] == ("k1", "k2")
    v = np.zeros(21)
    v[-2:] = [0.98, 0.17]
    v[0] = 0.05
    v /= np.linalg.norm(v)
    desc = ob.describe_direction(v, names)
    assert [k for k, _ in desc] == ["k1", "k2"]
    assert desc[0][1] == pytest.approx(0.98 / np.sqrt(0.98**2 + 0.17**2 + 0.05**2))
    basis = np.zeros((21, 2))
    basis[-2:, :] = np.eye(2)
    assert ob.subspace_share(v, basis) == pytest.approx((0.98**2 + 0.17**2) / (0.98**2 + 0.17**2 + 0.05**2))
