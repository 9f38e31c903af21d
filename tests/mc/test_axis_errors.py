"""Per-axis error against the filter's own 3-sigma (issue 33, item 4)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scenarios import random_states

from stereopose_mc.config import load_scenario
from stereopose_mc.core import aligned
from stereopose_mc.core import errorstate as es
from stereopose_mc.mc import engine
from stereopose_mc.mc.rows import trials_columns
from stereopose_mc.mc.trial import axis_errors, run_chunk
from stereopose_mc.rundir.tables import AXES, AXIS_UNITS

RAD2DEG = 180.0 / np.pi


def _spd(rng, B, m):
    A = rng.standard_normal((B, m, m))
    return A @ np.swapaxes(A, -1, -2) / m + 0.1 * np.eye(m)


def test_axis_errors_are_the_attitude_chart_error_and_its_sigma_in_every_chart():
    rng = np.random.default_rng(3)
    x_true = random_states(rng, B=5, N=3)
    n = x_true.shape[-1]
    eps = 1e-2 * rng.standard_normal((5, n - 1))
    x_hat = es.chart(x_true, eps)  # x_hat = x_true [+] eps: the error is eps
    P_att = _spd(rng, 5, n - 1)
    rows = np.r_[0:12, n - 3 : n - 1]
    scale = np.array([1.0] * 6 + [RAD2DEG] * 6 + [1.0] * 2)
    want_sigma = np.sqrt(np.diagonal(P_att, axis1=-2, axis2=-1)[:, rows]) * scale
    # the same covariance as the filter would hold it: attitude chart, aligned chart, full state
    P_al = aligned.from_attitude_chart(x_hat, P_att)
    S = es.chart_jacobian(x_hat)
    P_full = S @ P_att @ np.swapaxes(S, -1, -2)
    for P, chart in ((P_att, "attitude"), (P_al, "aligned"), (P_full, "full")):
        e, s = axis_errors(x_hat, P, x_true, chart)
        np.testing.assert_allclose(e, eps[:, rows] * scale, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(s, want_sigma, rtol=1e-8)
    assert len(AXES) == 14 and AXIS_UNITS["theta_z"] == "deg" and AXIS_UNITS["omega_x"] == "deg/s"


@pytest.mark.slow
def test_case_b_iekf_errors_stay_inside_3_sigma():
    """Case B, default IEKF, 30 trials: over t >= 10 s at least 95 % of the per-axis errors lie within +-3 sigma."""
    scn = load_scenario(Path(__file__).resolve().parents[2] / "configs" / "caseB.yaml", {"filters": [{"type": "iekf"}]})
    pr = engine.prepare(scn)
    res = run_chunk(scn.seed, np.arange(30), pr.setup, pr.truth, pr.exact, pr.filters, pr.bounds)
    r = res.runs[0]
    w = pr.truth.t >= 10.0 - 1e-9
    e, s = r.axis_err[r.lost_step < 0][:, w], r.axis_sigma[r.lost_step < 0][:, w]
    assert np.isfinite(e).all() and np.isfinite(s).all() and (s > 0).all()
    frac = float(np.mean(np.abs(e) <= 3 * s))
    assert frac >= 0.95, frac
    # trials.parquet's column is the same fraction per trial
    cols = trials_columns(res, pr.truth.t, 10.0, scn.seed)
    assert np.mean(cols["inside_3sigma"][r.lost_step < 0]) == pytest.approx(frac, rel=1e-12)
