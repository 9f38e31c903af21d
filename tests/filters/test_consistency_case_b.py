"""Issue 10's consistency target on case B: the default (aligned error state) IEKF, and the MEKF in that chart
iterated (the same filter; the default ``type: mekf`` is the classical plain MEKF in the attitude chart), are
consistent.

40 trials of configs/caseB.yaml (the thesis's wide P0, truth + N(0, P0) start), the default
Q and divergence rules. Per filter, the median over the converged trials of the
time-averaged (t >= 10 s) NEES per degree of freedom, gauge-projected and per block, must
be <= 2 (and >= 0.2: not grossly pessimistic), the median time-averaged NIS per
dimension inside the 95 % band of one trial, and at most 2 trials lost. The thesis's
full-state IEKF on the same draws is the counter-example: overconfident in the attitude.
(The 100-trial numbers are in docs/filters.md, Error state.)
"""

from __future__ import annotations


import numpy as np
import pytest

from stereopose_mc.config import load_scenario
from stereopose_mc.mc import engine
from stereopose_mc.mc.trial import run_chunk
from stereopose_mc.outputs import consistency

from stereopose_mc.core import errorstate as es

TRIALS = 40


def _summary(r, setup, w):
    ok = r.diverged_step < 0
    dof = es.nees_dof(setup.x0.size)

    def med(a):
        return float(np.median(np.nanmean(a[ok][:, w], axis=1)))

    nees = {k: med(r.nees if k == "nees" else r.nees_parts[k]) / d for k, d in dof.items()}
    with np.errstate(all="ignore"):
        nis = med(np.where(r.nis_dof > 0, r.nis / np.maximum(r.nis_dof, 1), np.nan))
    return int((~ok).sum()), nees, nis


@pytest.fixture(scope="module")
def case_b():
    from pathlib import Path

    scn = load_scenario(Path(__file__).resolve().parents[2] / "configs" / "caseB.yaml",
                        {"filters": [{"type": "iekf"}, {"type": "mekf", "error_state": "aligned", "iterated": True},
                                     {"type": "iekf", "name": "iekf_full", "error_state": "full"}]})  # fmt: skip
    pr = engine.prepare(scn)
    res = run_chunk(scn.seed, np.arange(TRIALS), pr.setup, pr.truth, pr.exact, pr.filters, pr.bounds)
    w = pr.truth.t >= pr.setup.window_start - 1e-9
    steps = int(w.sum())
    band = consistency.nis_band(float(np.mean(res.runs[0].nis_dof[w])), steps)
    return {r.label: _summary(r, pr.setup, w) for r in res.runs}, band


@pytest.mark.parametrize("label", ["iekf", "mekf"])
def test_default_filters_are_consistent_in_case_b(case_b, label):
    out, band = case_b
    lost, nees, nis = out[label]
    assert lost <= 2
    for key, v in nees.items():
        if key == "nees":  # the full NEES counts the error along the curved gauge orbit: reported, not judged
            continue
        assert 0.2 <= v <= 2.0, (key, v)
    assert band[0] <= nis <= band[1], (nis, band)


def test_the_thesis_full_state_iekf_is_overconfident_on_the_same_draws(case_b):
    out, _ = case_b
    _, nees, _ = out["iekf_full"]
    assert nees["nees_attitude"] > 3.0 and nees["nees_rho"] > 3.0
