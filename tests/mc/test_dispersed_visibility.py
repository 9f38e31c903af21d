"""Dispersed mesh targets: each trial's own visibility inside one batch.

A dispersed attitude gives every trial its own self-occlusion pattern. ``mc.dispersed`` runs
the trials of one filter model as one batch: at each step, one update per pattern of visible
features among them (``mc.trial._update``), or past 64 columns on the compiled kernels one update of
the union of their views, each trial's own view a row mask. Reference: the same trials run alone,
and one update per pattern.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml
from scenarios import CONFIGS, scenario_dict

from stereopose_mc.config import load_scenario_text
from stereopose_mc.mc import dispersed, engine

TRIALS = np.arange(6)
NIS_RATIO = 1.2  # tight: the lost rule fires for some trials and not for others


def mesh_scenario(outliers: bool = True, start: str | None = None, features: int = 12, nis_ratio: float = NIS_RATIO,
                  filters: list | None = None, dropout: float = 0.0):  # fmt: skip
    """The dispersed mesh target (self-occlusion, a dispersed attitude) on ``features`` features (12) over 14 s, with
    filters that start close to the truth and know the target (well-conditioned updates: round-off stays round-off);
    ``filters`` other filters, ``dropout`` the tracker's share of dropped features, ``nis_ratio`` the lost rule's."""
    d = scenario_dict("mission-mesh-dispersed", time={"dt_s": 1.0, "duration_s": 14.0, "error_window_start_s": 4.0},
                      trials=TRIALS.size)  # fmt: skip
    d["target"] = {**d["target"], "shape": {"type": "mesh", "file": str(CONFIGS / "meshes" / "box.obj")},
                   "feature_points": {"sample_on_surface": features}}  # fmt: skip
    d["initial_covariance"] = {"rho_m2": 0.01, "rho_dot_m2ps2": 1e-4, "omega_deg2ps2": 0.01, "q": 1e-6,
                               "feature_points_m2": 1e-4, "k": 0.01}  # fmt: skip
    # the filters pinned here (a gated IEKF and a plain gated MEKF with the default Q), not the example's tuned pair:
    # the tight lost rule below must fire for some trials and not for others
    d["filters"] = [{"type": "iekf", "tolerance": 0.01, "max_iterations": 10, "gating": {"probability": 0.999}},
                    {"type": "mekf", "gating": {"probability": 0.999}}]  # fmt: skip
    if filters is not None:
        d["filters"] = filters
    d["dispersions"] = {k: v for k, v in d["dispersions"].items() if k.startswith(("sampling", "truth_initial_state.q",
                                                                                   "truth_initial_state.omega"))}
    if not outliers:
        d["measurements"] = {k: v for k, v in d["measurements"].items() if k != "outliers"}
    if dropout:
        d["measurements"] = {**d["measurements"], "dropout_probability": dropout}
    if start is not None:
        d["initial_estimate"] = {"method": start}
    d["divergence"] = {"nis_window_steps": 4, "nis_start_s": 4.0, "nis_ratio": nis_ratio}  # some trials lost
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


def _spied(monkeypatch, module, name: str, calls: list):
    """``module.name`` wrapped to append its arguments to ``calls``."""
    f = getattr(module, name)

    def spy(*args, **kwargs):
        calls.append(args)
        return f(*args, **kwargs)

    monkeypatch.setattr(module, name, spy)


def _per_pattern(monkeypatch):
    """The compiled update of a dispersed batch once per pattern of visible features, at every size."""
    from stereopose_mc.filters import compiled

    monkeypatch.setattr(compiled, "masks_visibility", lambda fs, n: False)


def _assert_identical(a, b):
    for fa, fb in zip(a, b):
        for name in fa:
            assert np.array_equal(np.asarray(fa[name]), np.asarray(fb[name]), equal_nan=name not in (
                "lost_reason", "inconsistent_reason")), name  # fmt: skip


@pytest.fixture(scope="module")
def large():
    """24 features: 87 columns in the IEKF's full state, 86 in the MEKF's aligned error state (past 64); the tracker
    drops 10 % of the features (its mask within each trial's view); the lost rule tighter (most trials lost at steps 7
    to 11: the batch shrinks)."""
    return mesh_scenario(features=24, nis_ratio=1.0, dropout=0.1)


def test_a_large_state_batch_is_one_update_with_the_numbers_of_one_per_pattern(large, monkeypatch):
    """Past 64 columns the compiled update takes a dispersed batch as one (``compiled.masks_visibility``): each
    trial's features out of view are masked rows, which add exact zeros to every sum, so its numbers are those of
    one update per pattern, bit for bit, in one call per step instead of one per pattern."""
    from stereopose_mc.core.kernels import update as ku
    from stereopose_mc.filters import compiled
    from stereopose_mc.mc import trial

    p = engine.prepare(large)
    assert [compiled.masks_visibility(fs, n) for fs, n in zip(p.filters, (87, 86))] == [True, True]
    assert not compiled.masks_visibility(p.filters[0], 64)  # (up to 64 columns: per pattern)
    ukf = engine.prepare(mesh_scenario(features=24, filters=[{"type": "ukf"}])).filters[0]
    assert not compiled.masks_visibility(ukf, 87)  # (its updates are not the kernels')
    as_one, per_pattern = [], []
    with monkeypatch.context() as m:
        _spied(m, ku, "iekf_update_batch", as_one)
        one = _chunks(large, "compiled", [TRIALS.size])
    with monkeypatch.context() as m:
        _per_pattern(m)
        _spied(m, ku, "iekf_update_batch", per_pattern)
        ref = _chunks(large, "compiled", [TRIALS.size])
    _assert_identical(one, ref)
    assert len(per_pattern) > len(as_one) + 20  # (several patterns at most steps)
    with monkeypatch.context() as m:  # measurements out of view not given (NaN: a track file's): the same numbers
        as_one_update = trial._update_as_one

        def unseen_nan(update, xa, Pa, active, measured, seen, *rest):
            y = measured.y.copy()
            y[~seen] = np.nan
            return as_one_update(update, xa, Pa, active, dataclasses.replace(measured, y=y), seen, *rest)

        m.setattr(trial, "_update_as_one", unseen_nan)
        _assert_identical(_chunks(large, "compiled", [TRIALS.size]), ref)
    assert 0 < sum(np.count_nonzero(f["lost_step"] >= 0) for f in one) < 2 * TRIALS.size
    _assert_same(_chunks(large, "compiled", [1] * TRIALS.size), one)  # and the trials run alone


def test_a_trial_left_to_numpy_turns_its_step_back_to_one_update_per_pattern(large, monkeypatch):
    """A factorization the kernels report failed (forced here for every trial at t = 6 s) hands its trials to numpy's
    algebra, which is not blind to masked rows: that step is updated per pattern (``compiled.NotMaskable``), so the
    results are again those of one update per pattern, bit for bit."""
    from stereopose_mc.core.kernels import update as ku
    from stereopose_mc.filters import compiled
    from stereopose_mc.mc import trial

    now = {}
    kernel, update = ku.iekf_update_batch, compiled.compiled_update

    def failing(*args):
        out = kernel(*args)
        if now["t"] == 6.0:
            out[6][:] = False  # ok: every trial left to numpy
        return out

    def timed(x, P, step, *rest, **kw):
        now["t"] = step.t
        return update(x, P, step, *rest, **kw)

    def run(m):
        m.setattr(ku, "iekf_update_batch", failing)
        m.setattr(compiled, "compiled_update", timed)
        return _chunks(large, "compiled", [TRIALS.size])

    raised = []
    as_one = trial._update_as_one

    def watched(*args):
        try:
            return as_one(*args)
        except compiled.NotMaskable as exc:
            raised.append(str(exc))
            raise

    with monkeypatch.context() as m:
        m.setattr(trial, "_update_as_one", watched)
        one = run(m)
    with monkeypatch.context() as m:
        _per_pattern(m)
        ref = run(m)
    assert raised and all("factorization" in r for r in raised)
    _assert_identical(one, ref)
