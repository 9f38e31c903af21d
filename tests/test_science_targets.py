"""Science targets that earlier work met, rerun on the default (compiled) kernels so a regression fails CI.

Case B (thesis case B, 100 trials, the scenario's seed): the aligned-error-state IEKF loses at most 5
trials (it loses 1), its median gauge-projected NEES per degree of freedom over the trials not lost is
at most 2 (0.79), and its median fraction of per-axis errors inside +-3 sigma over t >= 10 s is at
least 0.95 (1.0). Case B with 5 % outliers (configs/caseB-outliers.yaml, 100 trials): the gated IEKF
loses at most 5 (0 with the pseudo rows' second-order R and the gate's inflation; 6 before either).
configs/mission-realistic.yaml (100 trials, `process_noise: auto`): the IEKF loses at most 5 (0; 23 before the
start from the first stereo frame and the second-order pseudo rows), and the issue's consistency and accuracy
targets hold with binomial margins (``test_mission_realistic_is_consistent_and_accurate``). configs/mission-debris.yaml (100
trials): the IEKF loses at most 5 and at most 15 of its trials are flagged inconsistent (0 and 3,
``test_mission_debris_iekf_stays_on_track_and_consistent``). configs/caseB-images.yaml (rendered images and the tracker; 100 trials:
0 lost, median gauge NEES/dof 1.85 over the occupied slots, docs/images.md), here on 20 trials: at most 3 lost (a
binomial bound for a 5 % rate: P(>= 4 of 20) = 1.6 %) and at most 14 trials with gauge NEES/dof above 2 (a median
<= 2 means a rate <= 0.5 above it: P(>= 15 of 20) = 2.1 %). The runs are deterministic per
machine; the margins absorb a trial that another machine's BLAS moves across a bound.
configs/mission-mesh-dispersed.yaml (100 trials, both filters: every update iterated, process noise on the rate
and the points): each loses at most 5 and the issue's consistency and accuracy targets hold with the same margins
as mission-realistic's (``test_mission_mesh_dispersed_filters_are_consistent_and_accurate``).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from scipy.stats import binomtest

from stereopose_mc import api

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """``campaign(scenario, trials)``: the trials table of ``configs/<scenario>.yaml`` run on ``trials`` trials, run
    once per module (mission-realistic's run serves two tests)."""
    done = {}

    def run(scenario: str, trials: int):
        if (scenario, trials) not in done:
            out = tmp_path_factory.mktemp("science") / scenario
            done[scenario, trials] = api.run(api.load(CONFIGS / f"{scenario}.yaml"), trials=trials, out=out).trials
        return done[scenario, trials]

    return run


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


# (scenario, filter label, trials, most trials lost): the targets of the issues that met them, at a trial count the
# suite affords; what each loses today is in the module docstring
LOST = [
    ("caseB-outliers", "iekf_gated", 100, 5),
    ("mission-realistic", "iekf", 100, 5),
]


@pytest.mark.slow
@pytest.mark.parametrize(("scenario", "label", "trials", "most"), LOST, ids=[r[0] for r in LOST])
def test_filter_stays_on_track(campaign, scenario, label, trials, most):
    t = campaign(scenario, trials)
    f = t[t["filter"] == label]
    assert len(f) == trials
    lost = int(f["lost"].sum())
    ci = binomtest(lost, trials).proportion_ci(0.95, method="wilson")
    assert lost <= most, (f"{lost} of {trials} lost (95% interval {ci.low:.1%}-{ci.high:.1%})",
                          f.loc[f["lost"], "lost_reason"].tolist())  # fmt: skip


def _gauge_nees_per_dof_above_2(kept, dof: str) -> int:
    """How many trials have a window-mean gauge NEES per degree of freedom (column ``dof``) above 2."""
    return int((kept["nees_gauge_mean"] / kept[dof] > 2.0).sum())


@pytest.mark.slow
def test_images_campaign_stays_on_track_and_consistent(tmp_path):
    """configs/caseB-images.yaml on 20 trials (1-2 minutes on 2 cores, most of it the tracker)."""
    run = api.run(api.load(CONFIGS / "caseB-images.yaml"), trials=20, out=tmp_path / "images")
    t = run.trials
    assert len(t) == 20
    assert int(t["lost"].sum()) <= 3, t.loc[t["lost"], "lost_reason"].tolist()
    kept = t[~t["lost"]]
    above = _gauge_nees_per_dof_above_2(kept, "dof_nees_gauge")  # the occupied slots' dof
    assert above <= 14, f"{above} of {len(kept)} trials with gauge NEES/dof above 2"


@pytest.mark.slow
def test_mission_realistic_is_consistent_and_accurate(campaign):
    """configs/mission-realistic.yaml, 100 trials (issue targets: >= 90 % of trials not flagged inconsistent, median
    gauge NEES/dof <= 2, attitude error median <= 1 deg and p90 <= 3 deg over the trials not lost; today 3
    inconsistent, 1.91, 0.79 and 1.58 deg). Each target as a count with a binomial margin: a 10 % rate gives more
    than 15 of 100 with probability 4 %, a 50 % rate more than 60 of 100 with probability 1.8 %."""
    t = campaign("mission-realistic", 100)  # (the run of test_filter_stays_on_track[mission-realistic])
    assert len(t) == 100
    assert int(t["inconsistent"].sum()) <= 15, t.loc[t["inconsistent"], "inconsistent_reason"].tolist()
    kept = t[~t["lost"]]
    above = _gauge_nees_per_dof_above_2(kept, "nees_gauge_dof")
    assert above <= 60, f"{above} of {len(kept)} trials with gauge NEES/dof above 2"
    assert int((kept["e_theta"] > 1.0).sum()) <= 60, kept["e_theta"].describe()
    assert int((kept["e_theta"] > 3.0).sum()) <= 15, kept["e_theta"].describe()



@pytest.mark.slow
def test_mission_debris_iekf_stays_on_track_and_consistent(tmp_path):
    """configs/mission-debris.yaml, 100 trials (issue targets: lost <= 5 %, >= 90 % of the IEKF's trials not flagged
    inconsistent; today 0 lost and 3 inconsistent; 1 and 8 before the prediction's second-order Q). Lost as the
    other rows' (at most 5 of 100); inconsistent as a count with a binomial margin: a 10 % rate flags more than 15
    of 100 with probability 4 %."""
    run = api.run(api.load(CONFIGS / "mission-debris.yaml"), trials=100, out=tmp_path / "debris")
    t = run.trials
    iekf = t[t["filter"] == "iekf"]
    assert len(iekf) == 100
    assert int(iekf["lost"].sum()) <= 5, iekf.loc[iekf["lost"], "lost_reason"].tolist()
    assert int(iekf["inconsistent"].sum()) <= 15, iekf.loc[iekf["inconsistent"], "inconsistent_reason"].tolist()


@pytest.mark.slow
def test_mission_mesh_dispersed_filters_are_consistent_and_accurate(tmp_path):
    """configs/mission-mesh-dispersed.yaml, 100 trials, the IEKF and the MEKF (issue targets: lost <= 5 %, >= 90 % of
    trials not flagged inconsistent, median gauge NEES/dof <= 2, attitude error median <= 1 deg and p90 <= 3 deg;
    today IEKF / MEKF: 3 / 2 lost, 11 / 11 inconsistent, 18 / 18 trials with gauge NEES/dof above 2, 41 / 42 with
    an attitude error above 1 deg and 6 / 7 above 3 deg. On 1,000 trials: 13 / 13 lost, 46 / 48 inconsistent;
    docs/realism.md has 300). The bounds as mission-realistic's: a 10 % rate flags more than 15 of 100 with
    probability 4 %, a 50 % rate gives more than 60 of 100 with probability 1.8 %. Without the filters' process
    noise the IEKF flags 52 of 300 (docs/realism.md), and the plain MEKF loses most trials."""
    run = api.run(api.load(CONFIGS / "mission-mesh-dispersed.yaml"), trials=100, out=tmp_path / "mesh")
    t = run.trials
    for label in ("iekf", "mekf"):
        f = t[t["filter"] == label]
        assert len(f) == 100
        assert int(f["lost"].sum()) <= 5, (label, f.loc[f["lost"], "lost_reason"].tolist())
        assert int(f["inconsistent"].sum()) <= 15, (label, f.loc[f["inconsistent"], "inconsistent_reason"].tolist())
        kept = f[~f["lost"]]
        above = _gauge_nees_per_dof_above_2(kept, "nees_gauge_dof")
        assert above <= 60, f"{label}: {above} of {len(kept)} trials with gauge NEES/dof above 2"
        assert int((kept["e_theta"] > 1.0).sum()) <= 60, (label, kept["e_theta"].describe())
        assert int((kept["e_theta"] > 3.0).sum()) <= 15, (label, kept["e_theta"].describe())
