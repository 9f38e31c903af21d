"""A filter type added from outside the package: one module (this one) and one registry entry.

The toy is an open-loop predictor: the filters' prediction (``relnav.predict``) and no update. It
runs through the engine (``mc.engine.compute_chunk``) from a scenario's YAML next to a built-in
IEKF; its errors must be those of its initial estimate propagated by the dynamics, integrated
here independently (scipy's DOP853 on ``core.dynamics.f``, tolerances 1e-12).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import pyarrow.compute as pc
import pytest
import yaml
from pydantic import Field
from scipy.integrate import solve_ivp

from stereopose_mc.config import ScenarioError, load_scenario_text
from stereopose_mc.config.filters import FilterBase
from stereopose_mc.core import dynamics, state as st
from stereopose_mc.filters import registry, relnav
from stereopose_mc.mc import engine
from stereopose_mc.sim import measurements as meas

from scenarios import scenario_dict

# ---------------------------------------------------------------- the toy filter: config model, step, entry


class OpenLoopConfig(FilterBase):
    """Open-loop predictor: the filters' prediction, no measurement update."""

    type: Literal["open_loop"]
    error_state: Literal["full"] = Field(default="full", description="its covariance is that of the full state")


def predict(x, P, t, fs, setup):
    return relnav.predict(x, P, t, fs, setup)


def update(x, P, step, rows, fs, setup, model=None):
    """No update: the prior is the posterior; no innovation (NIS NaN), every visible feature counted as used."""
    B = x.shape[0]
    return relnav.GatedUpdate(x, P, np.zeros((B, step.y.shape[-1])), np.full(B, np.nan), np.zeros(B, int),
                              np.ones(B, bool), np.zeros(B, int), np.full(B, int(step.visible.sum())))  # fmt: skip


OPEN_LOOP = registry.FilterType("open_loop", OpenLoopConfig, registry.Step(predict, update), compiled=None,
                                chart=registry.error_state_chart)  # fmt: skip

# ---------------------------------------------------------------------------------------------------------------

TIME = {"dt_s": 1.0, "duration_s": 6.0, "error_window_start_s": 1.0}
FILTERS = [{"type": "iekf"}, {"type": "open_loop", "name": "drift"}]


@pytest.fixture
def open_loop():
    registry.register(OPEN_LOOP)
    try:
        yield
    finally:
        registry.unregister("open_loop")


def _scenario(filters=FILTERS):
    return load_scenario_text(yaml.safe_dump(scenario_dict(time=TIME, filters=filters)))


def _errors(ts, label: str, trials) -> np.ndarray:
    """``(trials, steps, 3)``: e_rho, e_rho_dot, e_omega of filter ``label`` from a chunk's time series."""
    t = ts.filter(pc.equal(ts["filter"], label)).to_pandas().sort_values(["trial", "step"])
    return t[["e_rho", "e_rho_dot", "e_omega"]].to_numpy().reshape(len(trials), -1, 3)


def test_an_open_loop_filter_runs_through_the_engine_and_drifts_as_the_dynamics(open_loop):
    scn = _scenario()
    trials = np.arange(3)
    out = engine.compute_chunk(scn.model_dump_json(), trials, "full")
    setup, truth = engine.prepare(scn)[1:3]
    # the reference: the same initial estimates, propagated by an independent integrator
    x0_hat = meas.initial_estimates(setup, meas.draw_trials(scn.seed, trials, setup.x0.size, setup.steps,
                                                            setup.n_points))  # fmt: skip

    def rhs(t, x):
        return dynamics.f_at(x, t, setup.orbit)

    ref = np.stack([solve_ivp(rhs, (0.0, truth.t[-1]), x, method="DOP853", t_eval=truth.t, rtol=1e-12,
                              atol=1e-12).y.T for x in x0_hat])  # fmt: skip
    d = ref - truth.x[None]
    expected = np.stack([np.linalg.norm(d[..., s], axis=-1) for s in (st.RHO, st.RHO_DOT, st.OMEGA)], axis=-1)
    expected[..., 2] *= 180.0 / np.pi
    drift = _errors(out.timeseries_table, "drift", trials)
    assert drift.shape == (3, setup.steps + 1, 3)
    np.testing.assert_allclose(drift, expected, rtol=1e-7, atol=1e-10)
    assert np.all(drift[:, -1, 0] != drift[:, 0, 0])  # it did move
    # paired with the IEKF: the same initial estimate, and the IEKF's updates pull it elsewhere
    iekf = _errors(out.timeseries_table, "iekf", trials)
    np.testing.assert_array_equal(iekf[:, 0], drift[:, 0])
    assert np.all(np.abs(iekf[:, -1, 0] - drift[:, -1, 0]) > 1e-6)
    assert out.diverged == 0


def test_a_filter_without_a_compiled_step_runs_numpy_under_compiled_kernels_and_says_so(open_loop):
    scn = _scenario([{"type": "open_loop"}])
    trials = np.arange(2)
    ref = engine.compute_chunk(scn.model_dump_json(), trials, "full", kernels="numpy")
    numpy = _errors(ref.timeseries_table, "open_loop", trials)
    with pytest.warns(UserWarning, match="filter type 'open_loop' has no compiled step: its trials run the numpy step"):
        out = engine.compute_chunk(scn.model_dump_json(), trials, "full", kernels="compiled")
    np.testing.assert_array_equal(_errors(out.timeseries_table, "open_loop", trials), numpy)


def test_the_scenario_schema_knows_a_registered_type_only_while_it_is_registered(open_loop):
    scn = _scenario()
    assert [f.type for f in scn.filters] == ["iekf", "open_loop"]
    registry.unregister("open_loop")
    with pytest.raises(ScenarioError, match="unknown filter type 'open_loop'; expected one of 'iekf', 'ekf', 'mekf', "
                                            "'ukf'"):  # fmt: skip
        _scenario()
    with pytest.raises(ValueError, match="filter type 'ekf' is already registered"):
        registry.register(registry.FILTERS["ekf"])
    with pytest.raises(ValueError, match="filter type 'drift': its config model's type tag is 'open_loop'"):
        registry.register(registry.FilterType("drift", OpenLoopConfig, OPEN_LOOP.numpy, None, registry.error_state_chart))
