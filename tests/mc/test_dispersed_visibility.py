"""Dispersed mesh targets: each trial's own visibility inside one batch.

A dispersed attitude gives every trial its own self-occlusion pattern. ``mc.dispersed`` runs
the trials of one filter model as one batch: at each step, one update per pattern of visible
features among them (``mc.trial._update``). Reference: the same trials run alone.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from scenarios import CONFIGS, scenario_dict

from stereopose_mc.config import load_scenario_text
from stereopose_mc.mc import dispersed, engine

TRIALS = np.arange(6)
NIS_RATIO = 1.2  # tight: the lost rule fires for some trials and not for others


def mesh_scenario(outliers: bool = True, start: str | None = None):
    """The dispersed mesh target (self-occlusion, a dispersed attitude) on 12 features over 14 s, with filters
    that start close to the truth and know the target (well-conditioned updates: round-off stays round-off)."""
    d = scenario_dict("mission-mesh-dispersed", time={"dt_s": 1.0, "duration_s": 14.0, "error_window_start_s": 4.0},
                      trials=TRIALS.size)  # fmt: skip
    d["target"] = {**d["target"], "shape": {"type": "mesh", "file": str(CONFIGS / "meshes" / "box.obj")},
                   "feature_points": {"sample_on_surface": 12}}  # fmt: skip
    d["initial_covariance"] = {"rho_m2": 0.01, "rho_dot_m2ps2": 1e-4, "omega_deg2ps2": 0.01, "q": 1e-6,
                               "feature_points_m2": 1e-4, "k": 0.01}  # fmt: skip
    # the filters pinned here (a gated IEKF and a plain gated MEKF with the default Q), not the example's tuned pair:
    # the tight lost rule below must fire for some trials and not for others
    d["filters"] = [{"type": "iekf", "tolerance": 0.01, "max_iterations": 10, "gating": {"probability": 0.999}},
                    {"type": "mekf", "gating": {"probability": 0.999}}]  # fmt: skip
    d["dispersions"] = {k: v for k, v in d["dispersions"].items() if k.startswith(("sampling", "truth_initial_state.q",
                                                                                   "truth_initial_state.omega"))}
    if not outliers:
        d["measurements"] = {k: v for k, v in d["measurements"].items() if k != "outliers"}
    if start is not None:
        d["initial_estimate"] = {"method": start}
    d["divergence"] = {"nis_window_steps": 4, "nis_start_s": 4.0, "nis_ratio": NIS_RATIO}  # some trials lost
    return load_scenario_text(yaml.safe_dump(d, sort_keys=False), "<test>")


def _chunks(scn, kernels: str, sizes: list[int]):
    """``dispersed.run_chunk`` over ``TRIALS`` in consecutive chunks of ``sizes``, each filter's runs concatenated."""
    p = engine.prepare(scn)
    bounds = np.cumsum([0] + sizes)
    parts = [dispersed.run_chunk(scn, TRIALS[a:b], p.setup, p.bounds, kernels)[0] for a, b in zip(bounds, bounds[1:])]
    out = []
    for f in range(len(scn.filters)):
        runs = [c.runs[f] for c in parts]
        cat = {name: np.concatenate([getattr(r, name) for r in runs]) for name in
               ("errors", "nees", "nis", "dof", "gated", "iterations", "lost_step", "inconsistent_step")}  # fmt: skip
        cat["nis_dof"] = np.concatenate([np.broadcast_to(r.nis_dof, r.nis.shape) for r in runs])
        cat["lost_reason"] = [s for r in runs for s in r.lost_reason]
        cat["inconsistent_reason"] = [s for r in runs for s in r.inconsistent_reason]
        out.append(cat)
    return out


def _assert_same(a, b):
    for fa, fb in zip(a, b):
        for name in ("errors", "nees", "nis"):
            np.testing.assert_allclose(fa[name], fb[name], rtol=1e-7, atol=1e-9, err_msg=name)
        for name in ("dof", "nis_dof", "gated", "iterations", "lost_step", "inconsistent_step", "lost_reason",
                     "inconsistent_reason"):  # fmt: skip
            assert np.array_equal(np.asarray(fa[name]), np.asarray(fb[name])), name


@pytest.fixture(scope="module")
def scn():
    return mesh_scenario()


def test_the_trials_see_different_features(scn):
    """The premise: a batch of the scenario's trials holds several visibility patterns."""
    from stereopose_mc.config.resolve import setup_of
    from stereopose_mc.sim import dispersions as sd

    p = engine.prepare(scn)
    disp = sd.draw(scn, TRIALS)
    setups = [setup_of(t) for t in disp.truth]
    vis = sd.exact_measurements(setups, sd.truth_of(setups, p.setup.times, p.setup.truth_rtol)).visible
    assert len({v.tobytes() for v in vis}) >= 3
    assert (vis[:, 0].sum(axis=-1) >= 3).all() and not vis.all()  # (the measurement start needs 3 at t = 0)
    assert any(len({row.tobytes() for row in v}) > 1 for v in vis)  # and a trial whose own set changes in time
    assert len(set(disp.model_key)) == 1  # one filter model: one batch


@pytest.mark.parametrize("kernels", ["numpy", "compiled"])
def test_one_batch_equals_the_trials_run_alone(scn, kernels):
    alone = _chunks(scn, kernels, [1] * TRIALS.size)
    batch = _chunks(scn, kernels, [TRIALS.size])
    _assert_same(batch, alone)
    lost = [np.count_nonzero(f["lost_step"] >= 0) for f in batch]
    assert 0 < sum(lost) < 2 * TRIALS.size  # the lost rules fired for some trials and not for others
    assert (batch[0]["nis_dof"][:, 1:] > 0).all() and len(np.unique(batch[0]["nis_dof"][:, 1])) > 1  # per trial


def test_results_do_not_depend_on_chunking(scn):
    _assert_same(_chunks(scn, "compiled", [2, 4]), _chunks(scn, "compiled", [5, 1]))


def test_kernels_agree_on_per_trial_visibility(scn):
    a, b = _chunks(scn, "numpy", [TRIALS.size]), _chunks(scn, "compiled", [TRIALS.size])
    for fa, fb in zip(a, b):
        np.testing.assert_allclose(fa["errors"], fb["errors"], rtol=1e-6, atol=1e-8)
        assert np.array_equal(fa["lost_step"], fb["lost_step"])


def test_measurement_start_per_trial_visibility():
    """The start from the first frame triangulates each trial's own visible features."""
    scn = mesh_scenario(outliers=False, start="measurements")
    _assert_same(_chunks(scn, "compiled", [TRIALS.size]), _chunks(scn, "compiled", [1] * TRIALS.size))
