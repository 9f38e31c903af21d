"""Science targets that earlier work met, rerun on the default (compiled) kernels so a regression fails CI.

Case B (thesis case B, 100 trials, the scenario's seed): the aligned-error-state IEKF loses at most 5
trials (it loses 1), its median gauge-projected NEES per degree of freedom over the trials not lost is
at most 2 (0.79), and its median fraction of per-axis errors inside +-3 sigma over t >= 10 s is at
least 0.95 (1.0). Case B with 5 % outliers (configs/caseB-outliers.yaml, 100 trials): the gated IEKF
loses at most 5 (0 with the pseudo rows' second-order R and the gate's inflation; 6 before either).
configs/mission-realistic.yaml (50 trials): the IEKF loses at most 5 % (2 of 50; it loses 0; 23 of 100 before
the start from the first stereo frame and the second-order pseudo rows). configs/mission-debris.yaml (100
trials): the IEKF loses at most 5 (3). The runs are deterministic per
machine; the margins absorb a trial that another machine's BLAS moves across a bound. Targets not met today
(mission-realistic's consistency and attitude error, the dispersed scenarios: docs/realism.md) join this
table when the work that meets them lands.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from stereopose_mc import api

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.mark.slow
def test_case_b_iekf_stays_on_track_and_consistent(tmp_path):
    run = api.run(api.load(CONFIGS / "caseB.yaml"), trials=100, out=tmp_path / "caseB")
    t = run.trials
    iekf = t[t["filter"] == "iekf"]
    assert len(iekf) == 100
    assert int(iekf["lost"].sum()) <= 5, iekf.loc[iekf["lost"], "lost_reason"].tolist()
    kept = iekf[~iekf["lost"]]
    assert (kept["nees_gauge_mean"] / kept["nees_gauge_dof"]).median() <= 2.0
    assert kept["inside_3sigma"].median() >= 0.95


@pytest.mark.slow
def test_case_b_with_outliers_gated_iekf_stays_on_track(tmp_path):
    run = api.run(api.load(CONFIGS / "caseB-outliers.yaml"), trials=100, out=tmp_path / "outliers")
    t = run.trials
    gated = t[t["filter"] == "iekf_gated"]
    assert len(gated) == 100
    assert int(gated["lost"].sum()) <= 5, gated.loc[gated["lost"], "lost_reason"].tolist()


@pytest.mark.slow
def test_mission_realistic_iekf_stays_on_track(tmp_path):
    run = api.run(api.load(CONFIGS / "mission-realistic.yaml"), trials=50, out=tmp_path / "realistic")
    t = run.trials
    assert len(t) == 50
    assert int(t["lost"].sum()) <= 2, t.loc[t["lost"], "lost_reason"].tolist()


@pytest.mark.slow
def test_mission_debris_iekf_stays_on_track(tmp_path):
    """configs/mission-debris.yaml (dispersed tumble, inertia, geometry, range; 100 trials): the IEKF loses at
    most 5 (it loses 3; 18 of 500 in docs/sensitivity.md)."""
    run = api.run(api.load(CONFIGS / "mission-debris.yaml"), trials=100, out=tmp_path / "debris")
    t = run.trials
    iekf = t[t["filter"] == "iekf"]
    assert len(iekf) == 100
    assert int(iekf["lost"].sum()) <= 5, iekf.loc[iekf["lost"], "lost_reason"].tolist()
