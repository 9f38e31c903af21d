"""The angular-acceleration source of the pseudo-measurement (mc/alpha_source.py)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from stereopose_mc.config import ScenarioError, load_scenario, load_scenario_text
from stereopose_mc.config.resolve import filter_setup_of, setup_of
from stereopose_mc.core import differentiators as dif
from stereopose_mc.core import quaternion as qt
from stereopose_mc.mc.alpha_source import AlphaSource, alpha_source_of, alpha_step, pseudo_row_variance

from scenarios import CONFIGS, scenario_dict

DIFFERENTIATED = ["savitzky_golay", "tikhonov", "tracking_differentiator"]
B, W = 4, 9


def history(T: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A noisy slowly varying omega series ``(B, T, 3)`` and its variances."""
    rng = np.random.default_rng(seed)
    t = np.arange(T)[None, :, None]
    w = 1e-3 * np.sin(0.01 * t + np.arange(3)) + 1e-5 * rng.standard_normal((B, T, 3))
    v = np.full((B, T, 3), 1e-10) * (1 + np.arange(B))[:, None, None]
    return w, v


def run(source: AlphaSource, w: np.ndarray, v: np.ndarray, W_buf: int | None = None):
    """Call alpha_step as the trial loop does: a NaN-initialized buffer, newest sample last."""
    Wb = W_buf or source.window
    T = w.shape[1]
    wb = np.full((B, Wb, 3), np.nan)
    vb = np.full((B, Wb, 3), np.nan)
    td = None
    truth = np.arange(B * 3, dtype=float).reshape(B, 3)
    out_a, out_s = [], []
    for k in range(T):
        wb = np.concatenate([wb[:, 1:], w[:, k : k + 1]], axis=1)
        vb = np.concatenate([vb[:, 1:], v[:, k : k + 1]], axis=1)
        a, s2, td = alpha_step(source, k, wb, vb, td, truth)
        assert a.shape == (B, 3) and s2.shape == (B, 3)
        out_a.append(a)
        out_s.append(s2)
    return np.stack(out_a, 1), np.stack(out_s, 1), td


@pytest.mark.parametrize("method", DIFFERENTIATED)
def test_nan_during_warm_up_then_finite(method):
    src = AlphaSource(method=method, dt=1.0, window=W)
    w, v = history(30)
    a, s2, td = run(src, w, v)
    assert np.isnan(a[:, : W - 1]).all() and np.isnan(s2[:, : W - 1]).all()
    assert np.isfinite(a[:, W - 1 :]).all() and (s2[:, W - 1 :] > 0).all()
    if method == "tracking_differentiator":
        assert td.shape == (B, 5, 3)
    else:
        assert td is None


def test_linear_methods_apply_their_weights_to_the_newest_window():
    w, v = history(25)
    for src, c in [
        (AlphaSource(method="savitzky_golay", dt=0.5, window=W, polyorder=2), dif.savgol_weights(W, 2, 0.5)),
        (AlphaSource(method="tikhonov", dt=0.5, window=W, tikhonov_lambda=3.0), dif.tikhonov_weights(W, 3.0, 0.5)),
    ]:
        a, s2, _ = run(src, w, v, W_buf=W + 4)  # a longer buffer: only the newest W count
        k = 20
        np.testing.assert_allclose(a[:, k], np.einsum("j,bjd->bd", c, w[:, k - W + 1 : k + 1]), rtol=1e-12)
        np.testing.assert_allclose(s2[:, k], np.einsum("j,bjd->bd", c**2, v[:, k - W + 1 : k + 1]), rtol=1e-12)


def test_savitzky_golay_recovers_the_derivative_of_a_quadratic_omega():
    t = np.arange(20.0)
    w = np.broadcast_to((1e-3 + 2e-5 * t - 3e-8 * t**2)[None, :, None], (B, 20, 3)).copy()
    a, _, _ = run(AlphaSource(method="savitzky_golay", dt=1.0, window=W), w, np.full_like(w, 1e-12))
    np.testing.assert_allclose(a[:, 15], 2e-5 - 6e-8 * 15, rtol=1e-8)


def test_tracking_differentiator_follows_its_own_recursion_and_restarts_at_k0():
    src = AlphaSource(method="tracking_differentiator", dt=1.0, window=W, td_r=0.05, td_h0=1.5)
    w, v = history(30)
    a, s2, td = run(src, w, v)
    ref, state = dif.td_series(w, 1.0, 0.05, 1.5)
    np.testing.assert_allclose(a[:, W - 1 :], ref[:, W - 1 :], rtol=1e-12)
    np.testing.assert_allclose(td[:, :2], state, rtol=1e-12)
    S = dif.td_covariance_init(v[:, 0])
    for k in range(1, 30):
        S = dif.td_covariance_step(S, v[:, k], 1.0, 1.5)
    np.testing.assert_allclose(s2[:, -1], S[:, 2], rtol=1e-12)
    # k = 0 restarts whatever state is passed
    a0, s0, td0 = alpha_step(src, 0, w[:, :W], v[:, :W], td, np.zeros((B, 3)))
    np.testing.assert_array_equal(td0[:, 0], w[:, W - 1])
    np.testing.assert_array_equal(td0[:, 2], v[:, W - 1])  # S11 = the sample's variance
    assert (td0[:, 1] == 0).all() and (td0[:, 3:] == 0).all() and np.isnan(a0).all()


def test_truth_plus_noise_passes_through():
    src = AlphaSource(method="truth_plus_noise", sigma_alpha=3e-6)
    truth = np.random.default_rng(1).standard_normal((B, 3))
    a, s2, td = alpha_step(src, 0, np.full((B, 1, 3), np.nan), np.full((B, 1, 3), np.nan), "state", truth)
    np.testing.assert_array_equal(a, truth)
    assert a is not truth
    np.testing.assert_array_equal(s2, np.full((B, 3), 3e-6**2))  # what relnav uses today
    assert td == "state" and not src.differentiated and src.warmup_steps == 1


@pytest.mark.parametrize("method", ["savitzky_golay", "tracking_differentiator"])
def test_a_trial_with_a_non_finite_sample_gets_nan_alone(method):
    src = AlphaSource(method=method, dt=1.0, window=W)
    w, v = history(20)
    w[2, 12] = np.nan
    a, s2, _ = run(src, w, v)
    assert np.isnan(a[2, 12:]).all() and np.isnan(s2[2, 12:]).all()
    others = [0, 1, 3]
    assert np.isfinite(a[others, W - 1 :]).all()


def test_sigma_floor_bounds_the_variance_from_below():
    src = AlphaSource(method="savitzky_golay", dt=1.0, window=W, sigma_floor=1e-3)
    w, v = history(12)
    _, s2, _ = run(src, w, v)
    np.testing.assert_array_equal(s2[:, -1], 1e-6)


def test_bad_sources_are_rejected():
    with pytest.raises(ValueError):
        AlphaSource(method="finite_difference")
    with pytest.raises(ValueError):
        AlphaSource(method="tracking_differentiator", dt=1.0, td_h0=0.4)  # dt/h0 > 2: unstable
    with pytest.raises(ValueError):
        AlphaSource(method="savitzky_golay", window=5, polyorder=5)
    src = AlphaSource(method="savitzky_golay", window=W)
    with pytest.raises(ValueError):
        alpha_step(src, 20, np.zeros((B, W - 1, 3)), np.zeros((B, W - 1, 3)), None, np.zeros((B, 3)))


@settings(max_examples=30, deadline=None)
@given(
    q=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1),
    s=st.lists(st.floats(1e-12, 1e-6), min_size=3, max_size=3),
)
def test_pseudo_row_variance_bounds_the_rotated_covariance(q, s):
    # the pseudo rows carry D^T alpha: covariance D^T diag(s) D <= max(s) I
    D = qt.dcm(np.asarray(q))
    cov = D.T @ np.diag(s) @ D
    R = pseudo_row_variance(np.asarray(s)[None], floor=0.0)[0]
    assert np.allclose(R, max(s))
    assert np.linalg.eigvalsh(np.diag(R) - cov).min() >= -1e-12 * max(s)
    assert pseudo_row_variance(np.asarray(s)[None], floor=1e-2)[0, 0] == pytest.approx(1e-4)


# ------------------------------------------------------------------ scenario -> source


def test_source_from_the_bundled_differentiated_scenario():
    scn = load_scenario(CONFIGS / "caseB-differentiated.yaml")
    setup = setup_of(scn)
    src = alpha_source_of(setup, filter_setup_of(scn.filters[0], setup))
    assert (src.method, src.window, src.polyorder, src.dt) == ("savitzky_golay", 9, 2, 1.0)
    np.testing.assert_allclose(src.weights, dif.savgol_weights(9, 2, 1.0))
    assert src.warmup_steps == 9


def test_schema_options_reach_the_source_in_si():
    d = scenario_dict(time={"dt_s": 0.5, "duration_s": 20.0, "error_window_start_s": 5.0})
    d["measurements"]["inertia_pseudo_measurement"].update(
        angular_acceleration="tracking_differentiator", window=6, td_r_radps3=0.2, td_h0_steps=3.0,
        sigma_floor_radps2=1e-8,
    )  # fmt: skip
    d["filters"] = [{"type": "iekf", "measurement_noise": {"angular_acceleration_sigma_radps2": 5e-6}}]
    scn = load_scenario_text(yaml.safe_dump(d))
    setup = setup_of(scn)
    src = alpha_source_of(setup, filter_setup_of(scn.filters[0], setup))
    assert (src.method, src.window, src.td_r, src.td_h0, src.dt) == ("tracking_differentiator", 6, 0.2, 1.5, 0.5)
    assert (src.sigma_floor, src.sigma_alpha) == (1e-8, 5e-6)
    default = setup_of(load_scenario_text(yaml.safe_dump(scenario_dict())))
    assert default.alpha_method == "truth_plus_noise"


@pytest.mark.parametrize(
    "opts",
    [
        {"window": 5, "polyorder": 5},
        {"angular_acceleration": "finite_difference"},
        {"td_h0_steps": 0.5},
        {"tikhonov_lambda": 0.0},
        {"angular_acceleration": "tikhonov", "window": 3, "tikhonov_order": 2},
    ],
)
def test_schema_rejects_bad_differentiator_options(opts):
    d = scenario_dict()
    d["measurements"]["inertia_pseudo_measurement"].update(opts)
    with pytest.raises(ScenarioError):
        load_scenario_text(yaml.safe_dump(d))
