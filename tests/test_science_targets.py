"""Science targets that earlier work met, rerun on the default (compiled) kernels so a regression fails CI.

Case B (thesis case B, 100 trials, the scenario's seed): the aligned-error-state IEKF loses at most 5
trials (it loses 1), its median gauge-projected NEES per degree of freedom over the trials not lost is
at most 2 (0.79), and its median fraction of per-axis errors inside +-3 sigma over t >= 10 s is at
least 0.95 (1.0). The runs are deterministic per machine; the margins absorb a trial that another
machine's BLAS moves across a bound. Targets not met today (case B with 5 % outliers, gated IEKF:
lost 6 against <= 5; the realistic scenarios) join this table when the work that meets them lands.
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
