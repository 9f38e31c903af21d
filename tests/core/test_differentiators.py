"""Causal differentiators of thesis appendix B (core/differentiators.py).

References are independent of the code under test: analytic derivatives of polynomials,
ramps and sines, a Vandermonde least-squares fit (numpy ``lstsq``) for the
Savitzky-Golay weights, the explicit minimum-``||D s||`` interpolant for Tikhonov's
``lam -> 0`` limit and a constrained least-squares fit for ``lam -> inf``, the complex
frequency response of the differentiator's linear zone, and Monte Carlo variances.
"""

from __future__ import annotations

from math import factorial

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stereopose_mc.core import differentiators as df

FAST = settings(max_examples=40, deadline=None)


def poly_window(coef: np.ndarray, W: int, dt: float, t_end: float) -> tuple[np.ndarray, float]:
    """Samples ``(W,)`` of ``sum_m coef_m t^m`` at ``t_end - (W-1-j) dt`` and its derivative at ``t_end``."""
    t = t_end + (np.arange(W) - (W - 1)) * dt
    p = np.polynomial.Polynomial(coef)
    return p(t), float(p.deriv()(t_end))


# --------------------------------------------------------------------------- Savitzky-Golay


@FAST
@given(
    W=st.integers(3, 15),
    p=st.integers(1, 4),
    dt=st.floats(0.05, 5.0),
    t_end=st.floats(-20.0, 20.0),
    coef=st.lists(st.floats(-2.0, 2.0), min_size=5, max_size=5),
)
def test_savgol_differentiates_polynomials_up_to_its_degree_exactly(W, p, dt, t_end, coef):
    if p >= W:
        p = W - 1
    c = df.savgol_weights(W, p, dt)
    w, d_true = poly_window(np.array(coef[: p + 1]), W, dt, t_end)
    scale = max(1.0, np.abs(w).max() / dt)
    assert abs(c @ w - d_true) <= 1e-9 * scale


@pytest.mark.parametrize("W,p,dt", [(5, 2, 1.0), (9, 2, 0.5), (9, 3, 2.0), (15, 1, 1.0)])
def test_savgol_weights_equal_the_least_squares_polynomial_slope(W, p, dt):
    # independent: fit b = lstsq(V, w) with V_jm = tau_j^m; the slope at tau = 0 is b_1
    tau = (np.arange(W) - (W - 1)) * dt
    V = tau[:, None] ** np.arange(p + 1)
    E = np.eye(W)
    ref = np.array([np.linalg.lstsq(V, E[:, j], rcond=None)[0][1] for j in range(W)])
    np.testing.assert_allclose(df.savgol_weights(W, p, dt), ref, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("bad", [(5, 0, 1.0), (5, 5, 1.0), (5, 2, 0.0)])
def test_savgol_rejects_bad_options(bad):
    with pytest.raises(ValueError):
        df.savgol_weights(*bad)


# --------------------------------------------------------------------------- Tikhonov


def test_integration_operator_is_the_trapezoid_rule():
    A = df.integration_operator(4)
    np.testing.assert_array_equal(A, [[0.5, 0.5, 0, 0], [0.5, 1, 0.5, 0], [0.5, 1, 1, 0.5]])
    np.testing.assert_array_equal(df.difference_operator(4, 2), [[1, -2, 1, 0], [0, 1, -2, 1]])


@FAST
@given(
    W=st.integers(4, 15),
    order=st.sampled_from([1, 2]),
    lam=st.floats(1e-4, 1e6),
    dt=st.floats(0.05, 5.0),
    t_end=st.floats(-10.0, 10.0),
    coef=st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3),
)
def test_tikhonov_is_exact_for_polynomials_up_to_the_difference_order_for_any_lambda(W, order, lam, dt, t_end, coef):
    # the derivative of a degree <= order polynomial is integrated exactly by the trapezoid
    # rule (it is of degree <= 1) and annihilated by D, so it makes the cost zero
    c = df.tikhonov_weights(W, lam, dt, order)
    w, d_true = poly_window(np.array(coef[: order + 1]), W, dt, t_end)
    assert abs(c @ w - d_true) <= 1e-8 * max(1.0, np.abs(w).max() / dt)


def min_norm_interpolant(w: np.ndarray, order: int) -> np.ndarray:
    """The lam -> 0 limit in step units, built by hand (no Tikhonov solve).

    ``A`` (W-1 x W) has full row rank, so the limit of the regularized solutions is the
    solution of ``A s = y`` with the least ``||D s||``. All solutions of ``A s = y`` are
    ``s_p + t n``: ``s_p`` from the trapezoid recurrence ``(s_j + s_{j+1})/2 = w_{j+1} - w_j``
    with ``s_0 = 0``, and the null vector ``n = (+1, -1, +1, ...)``.
    """
    W = w.size
    sp = np.zeros(W)
    for j in range(W - 1):
        sp[j + 1] = 2.0 * (w[j + 1] - w[j]) - sp[j]
    n = (-1.0) ** np.arange(W)
    D = np.diff(np.eye(W), n=order, axis=0)
    t = -(D @ n) @ (D @ sp) / ((D @ n) @ (D @ n))
    return sp + t * n


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("W", [5, 9])
def test_tikhonov_tends_to_the_minimum_roughness_trapezoid_interpolant_as_lambda_vanishes(W, order):
    rng = np.random.default_rng(7)
    w = rng.standard_normal(W)
    ref = min_norm_interpolant(w, order)
    dt = 0.5
    errs, resid = [], []
    for lam in (1e-4, 1e-6, 1e-8):
        s = df.tikhonov_solve(w[:, None], lam, dt, order)[:, 0] * dt
        errs.append(np.abs(s - ref).max())
        # the limit interpolates: consecutive trapezoid means are the finite differences
        resid.append(np.abs((s[:-1] + s[1:]) / 2 - np.diff(w)).max())
    scale = np.abs(ref).max()
    assert errs[-1] < 1e-4 * scale and resid[-1] < 1e-5 * scale
    # both vanish like lam (first-order perturbation of the constrained minimizer)
    for e in (errs, resid):
        assert 50 < e[0] / e[1] < 200 and 50 < e[1] / e[2] < 200


def test_tikhonov_tends_to_a_pinned_quadratic_fit_as_lambda_grows():
    # lam -> inf with second differences forces s linear: w - w_0 = s0 t + s1 t^2 / 2 (in steps),
    # a least-squares fit through w_0; the derivative at the newest sample is s0 + s1 (W-1)
    W, dt = 9, 2.0
    rng = np.random.default_rng(3)
    w = rng.standard_normal(W)
    t = np.arange(1, W)
    b = np.linalg.lstsq(np.stack([t, t**2 / 2.0], axis=1), w[1:] - w[0], rcond=None)[0]
    ref = (b[0] + b[1] * (W - 1)) / dt
    assert abs(df.tikhonov_weights(W, 1e9, dt, 2) @ w - ref) < 1e-6 * max(1.0, abs(ref))


@pytest.mark.parametrize("lam,order", [(0.01, 1), (1.0, 2), (100.0, 2)])
def test_tikhonov_weights_are_the_newest_sample_of_the_full_solution(lam, order):
    rng = np.random.default_rng(11)
    w = rng.standard_normal((4, 9, 3))
    c = df.tikhonov_weights(9, lam, 0.7, order)
    full = df.tikhonov_solve(w, lam, 0.7, order)
    np.testing.assert_allclose(df.apply_weights(c, w), full[..., -1, :], rtol=1e-10, atol=1e-12)
    assert abs(c.sum()) < 1e-12 * np.abs(c).sum()  # a constant has zero derivative


def test_tikhonov_rejects_bad_options():
    with pytest.raises(ValueError):
        df.tikhonov_weights(9, 0.0, 1.0)
    with pytest.raises(ValueError):
        df.tikhonov_weights(3, 1.0, 1.0, order=2)
    with pytest.raises(ValueError):
        df.difference_operator(5, 3)


# --------------------------------------------------------------------------- sines and noise (linear)


LINEAR = {
    "savgol_9_2": (lambda dt: df.savgol_weights(9, 2, dt), 2),
    "savgol_5_1": (lambda dt: df.savgol_weights(5, 1, dt), 1),
    "tikhonov_9_2": (lambda dt: df.tikhonov_weights(9, 100.0, dt, 2), 2),
    "tikhonov_9_1": (lambda dt: df.tikhonov_weights(9, 10.0, dt, 1), 1),
}


@pytest.mark.parametrize("name", list(LINEAR))
def test_sine_derivative_within_the_taylor_remainder_bound(name):
    # exact for degree <= p, so the error is sum_j c_j R(tau_j) with |R| <= A W^{p+1} |tau|^{p+1} / (p+1)!
    make, p = LINEAR[name]
    dt, A, Om = 0.5, 2.0, 0.1
    c = make(dt)
    W = c.size
    tau = (np.arange(W) - (W - 1)) * dt
    bound = A * Om ** (p + 1) * np.sum(np.abs(c) * np.abs(tau) ** (p + 1)) / factorial(p + 1)
    assert bound == pytest.approx(df.truncation_bound(c, dt, p, A * Om ** (p + 1)), rel=1e-12)
    assert bound < 0.3 * A * Om  # the bound says something
    worst = 0.0
    for t_end in np.linspace(0.0, 2 * np.pi / Om, 37):
        w = A * np.sin(Om * (t_end + tau) + 0.4)
        err = abs(c @ w - A * Om * np.cos(Om * t_end + 0.4))
        assert err <= bound * (1 + 1e-9)
        worst = max(worst, err)
    assert worst > 1e-3 * bound  # not vacuous: the estimator is not exact on a sine


@pytest.mark.parametrize("name", ["savgol_9_2", "tikhonov_9_2", "tikhonov_9_1"])
def test_linear_noise_variance_matches_monte_carlo(name):
    make, _ = LINEAR[name]
    dt = 0.5
    c = make(dt)
    W = c.size
    sig = np.linspace(1.0, 3.0, W)  # heteroscedastic samples
    rng = np.random.default_rng(2024)
    n = 40000
    noise = rng.standard_normal((n, W, 1)) * sig[None, :, None]
    est = df.apply_weights(c, noise)[:, 0]
    pred = df.weights_variance(c, np.broadcast_to((sig**2)[:, None], (W, 1)))[0]
    # the sample variance of n Gaussians has relative sd sqrt(2/n) = 0.7 %
    assert np.var(est) == pytest.approx(pred, rel=5 * np.sqrt(2.0 / n))


@pytest.mark.parametrize("lead", [(), (4,), (2, 3)])
def test_linear_kernels_keep_batch_axes(lead):
    rng = np.random.default_rng(0)
    c = df.savgol_weights(7, 2, 1.0)
    w = rng.standard_normal(lead + (7, 3))
    out = df.apply_weights(c, w)
    assert out.shape == lead + (3,)
    assert df.weights_variance(c, w**2).shape == lead + (3,)
    flat = w.reshape(-1, 7, 3)
    np.testing.assert_allclose(out.reshape(-1, 3), [c @ flat[i] for i in range(flat.shape[0])], rtol=1e-12)
    series = rng.standard_normal(lead + (20, 3))
    assert df.causal_series(c, series).shape == lead + (20, 3)
    with pytest.raises(ValueError):
        df.apply_weights(c, w[..., :5, :])


def test_causal_series_uses_only_the_past():
    rng = np.random.default_rng(5)
    x = rng.standard_normal((2, 30, 3))
    for c in (df.savgol_weights(9, 2, 1.0), df.tikhonov_weights(9, 100.0, 1.0)):
        base = df.causal_series(c, x)
        assert np.isnan(base[:, :8]).all() and np.isfinite(base[:, 8:]).all()
        y = x.copy()
        y[:, 20:] += 5.0 * rng.standard_normal((2, 10, 3))  # change the future of sample 19
        out = df.causal_series(c, y)
        np.testing.assert_array_equal(out[:, :20], base[:, :20])
        assert np.all(np.abs(out[:, 20] - base[:, 20]) > 0)
        np.testing.assert_allclose(base[:, 12], df.apply_weights(c, x[:, 4:13]), rtol=1e-12)


# --------------------------------------------------------------------------- Han's tracking differentiator


@FAST
@given(
    x1=st.floats(-10.0, 10.0),
    x2=st.floats(-10.0, 10.0),
    r=st.floats(1e-3, 1e3),
    h0=st.floats(0.1, 10.0),
)
def test_fhan_is_bounded_by_r_and_linear_near_the_origin(x1, x2, r, h0):
    f = float(df.fhan(np.array(x1), np.array(x2), r, h0))
    assert abs(f) <= r * (1 + 1e-12)
    # scale the point into the linear zone |y| < d, |x1 + 2 h0 x2| < d, d = r h0^2
    d = r * h0 * h0
    s = 0.3 * d / (abs(x1) + 2 * h0 * abs(x2) + 1e-300)
    a, b = x1 * s, x2 * s
    lin = -a / h0**2 - 2 * b / h0
    assert float(df.fhan(np.array(a), np.array(b), r, h0)) == pytest.approx(lin, rel=1e-9, abs=1e-12 * r)


def test_td_linear_zone_is_the_stated_linear_system():
    dt, h0 = 0.5, 1.5
    Phi, b = df.td_linear_system(dt, h0)
    rng = np.random.default_rng(1)
    s = rng.standard_normal((50, 2, 1)) * 1e-3
    v = rng.standard_normal((50, 1)) * 1e-3
    s_new, out = df.td_step(s, v, dt, r=1e3, h0=h0)  # r h0^2 >> |x|: linear zone
    ref = np.einsum("ij,bjk->bik", Phi, s) + b[None, :, None] * v[:, None, :]
    np.testing.assert_allclose(s_new, ref, rtol=1e-10, atol=1e-15)
    np.testing.assert_array_equal(out, s_new[:, 1])
    # critically damped: a double eigenvalue 1 - dt/h0
    np.testing.assert_allclose(np.linalg.eigvals(Phi), [1 - dt / h0] * 2, atol=1e-6)


def test_td_tracks_a_sine_after_its_transient():
    # linear zone: steady state is the frequency response y = Im(A H e^{i(theta k + phi)}),
    # H = e^{i theta} [(e^{i theta} I - Phi)^-1 b]_2 (the output is x2 after sample k)
    dt, h0, A, Om, phi = 1.0, 1.5, 1.0, 0.05, 0.3
    theta = Om * dt
    Phi, b = df.td_linear_system(dt, h0)
    H = np.exp(1j * theta) * np.linalg.solve(np.exp(1j * theta) * np.eye(2) - Phi, b.astype(complex))[1]
    k = np.arange(400)
    x = A * np.sin(theta * k + phi)
    out, _ = df.td_series(x[:, None], dt, r=10.0, h0=h0)
    steady = np.imag(A * H * np.exp(1j * (theta * k + phi)))
    true = A * Om * np.cos(theta * k + phi)
    late = k >= 100  # transient ~ (1 - dt/h0)^k = 3^-k
    np.testing.assert_allclose(out[late, 0], steady[late], atol=1e-12)
    bound = A * abs(H - 1j * Om)  # steady tracking error amplitude
    assert bound < 0.1 * A * Om
    assert np.abs(out[late, 0] - true[late]).max() <= bound * (1 + 1e-9)
    assert np.abs(out[:5, 0] - true[:5]).max() > bound  # there is a transient


def test_td_recovers_a_ramp_slope_exactly_after_its_transient():
    # the linear zone is a type-2 loop: sum_m g_m = 0 and sum_m m dt g_m = -1
    dt, h0 = 0.5, 2.0
    g = df.td_impulse_response(dt, h0, 2000)
    assert abs(g.sum()) < 1e-12 and np.sum(np.arange(2000) * dt * g) == pytest.approx(-1.0, abs=1e-10)
    t = np.arange(300) * dt
    out, _ = df.td_series((0.3 + 0.02 * t)[:, None], dt, r=10.0, h0=h0)
    assert abs(out[-1, 0] - 0.02) < 1e-12


def test_td_saturated_step_respects_the_rate_bound_and_settles():
    # |fhan| <= r bounds each step's change of x2 by r dt; reaching rest at a step of size S
    # with that bound takes at least 2 sqrt(S / r) (bang-bang time)
    dt, r, h0, S = 0.5, 1e-3, 1.0, 2.0
    x = np.full((4000, 1), S)
    x[0] = 0.0
    out, _ = df.td_series(x, dt, r, h0)
    states = []
    s = df.td_init(x[0])
    for v in x[1:]:
        s, _ = df.td_step(s, v, dt, r, h0)
        states.append(s[:, 0])
    states = np.array(states)
    assert np.abs(np.diff(out[:, 0])).max() <= r * dt * (1 + 1e-12)
    assert np.abs(states[-1] - [S, 0.0]).max() < 1e-12
    at_rest = np.flatnonzero((np.abs(states[:, 0] - S) < 1e-6) & (np.abs(states[:, 1]) < 1e-6))[0] + 1
    assert at_rest * dt >= 2 * np.sqrt((S - 1e-6) / r) - dt
    assert at_rest * dt <= 1.5 * 2 * np.sqrt(S / r)


def test_td_is_causal():
    rng = np.random.default_rng(9)
    x = rng.standard_normal((3, 60, 3))
    base, _ = df.td_series(x, 1.0, 0.5, 2.0)
    y = x.copy()
    y[:, 40:] = 10.0
    out, _ = df.td_series(y, 1.0, 0.5, 2.0)
    np.testing.assert_array_equal(out[:, :40], base[:, :40])
    assert np.all(out[:, 40] != base[:, 40])


@pytest.mark.parametrize("lead", [(), (5,), (2, 3)])
def test_td_keeps_batch_axes_and_trials_independent(lead):
    rng = np.random.default_rng(4)
    x = rng.standard_normal(lead + (25, 3))
    out, s = df.td_series(x, 1.0, 0.2, 2.0)
    assert out.shape == lead + (25, 3) and s.shape == lead + (2, 3)
    flat = x.reshape(-1, 25, 3)
    one = np.stack([df.td_series(flat[i], 1.0, 0.2, 2.0)[0] for i in range(flat.shape[0])])
    np.testing.assert_allclose(out.reshape(-1, 25, 3), one, rtol=1e-13)
    S = df.td_covariance_step(df.td_covariance_init(x[..., 0, :] ** 2), x[..., 1, :] ** 2, 1.0, 2.0)
    assert S.shape == lead + (3, 3)


def test_td_covariance_step_is_phi_s_phi_t_plus_b_b_t_var():
    dt, h0 = 0.7, 2.5
    Phi, b = df.td_linear_system(dt, h0)
    rng = np.random.default_rng(8)
    L = rng.standard_normal((2, 2))
    S = L @ L.T
    var = 0.37
    ref = Phi @ S @ Phi.T + np.outer(b, b) * var
    packed = np.array([[S[0, 0]], [S[0, 1]], [S[1, 1]]])
    out = df.td_covariance_step(packed, np.array([var]), dt, h0)[:, 0]
    np.testing.assert_allclose(out, [ref[0, 0], ref[0, 1], ref[1, 1]], rtol=1e-12)


def test_td_variance_recursion_matches_monte_carlo_with_a_decaying_input_variance():
    # linear zone, independent errors whose variance falls 100-fold: the initial-sample
    # transient dominates early and is what a window-only model would miss
    dt, h0, T, n = 1.0, 2.0, 30, 20000
    sig = 10.0 * np.exp(-np.arange(T) / 6.0) + 0.1
    rng = np.random.default_rng(99)
    e = rng.standard_normal((n, T, 1)) * sig[None, :, None]
    out, _ = df.td_series(e, dt, r=1e6, h0=h0)
    S = df.td_covariance_init(np.array([sig[0] ** 2]))
    pred = [S[2, 0]]
    for k in range(1, T):
        S = df.td_covariance_step(S, np.array([sig[k] ** 2]), dt, h0)
        pred.append(S[2, 0])
    pred = np.array(pred)
    mc = out[:, :, 0].var(axis=0)
    np.testing.assert_allclose(mc[1:], pred[1:], rtol=5 * np.sqrt(2.0 / n))
    assert pred[0] == 0.0 and mc[0] == 0.0


def test_td_noise_gain_is_the_stationary_sum_of_squared_impulse_response():
    for dt, h0 in [(1.0, 1.5), (0.5, 2.0), (1.0, 4.0)]:
        g = df.td_impulse_response(dt, h0, 3000)
        assert df.td_noise_gain(dt, h0) == pytest.approx(np.sum(g**2), rel=1e-10)
    with pytest.raises(ValueError):
        df.td_noise_gain(1.0, 0.5)  # dt / h0 = 2: not stable


@pytest.mark.parametrize("r,ratio_max", [(1e3, 1.0), (0.1, 1.0), (0.01, 0.5)])
def test_td_saturation_only_lowers_the_noise_response(r, ratio_max):
    # white noise sigma = 1 with h0 = 4: linear zone |y| < r h0^2 (16000, 1.6, 0.16)
    dt, h0, n = 1.0, 4.0, 4000
    rng = np.random.default_rng(12)
    out, _ = df.td_series(rng.standard_normal((n, 150, 1)), dt, r, h0)
    G = df.td_noise_gain(dt, h0)
    ratio = out[:, -1, 0].var() / G
    assert ratio <= ratio_max * (1 + 5 * np.sqrt(2.0 / n))
    if r == 1e3:  # fully linear: the gain is the variance
        assert ratio == pytest.approx(1.0, rel=5 * np.sqrt(2.0 / n))
