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
