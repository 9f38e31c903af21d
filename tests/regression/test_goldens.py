"""CI regression: reduced thesis cases A-F rerun and compared with their golden percentile tables.

The goldens (``tests/regression/goldens/caseX.csv``) are written by ``make goldens``
(``python -m stereopose_mc.outputs.goldens refresh``); see docs/outputs.md for when and how
to refresh them. The runs are deterministic on one machine; the tolerance (rtol 1e-3) absorbs
the BLAS round-off that differs between machines and nothing more.
"""

from __future__ import annotations

import shutil

import pandas as pd
import pytest
from typer.testing import CliRunner

import stereopose_mc.cli.report_cmds  # noqa: F401  (registers 'compare')
from stereopose_mc.outputs import goldens as reg
from stereopose_mc.cli.main import app
from stereopose_mc.outputs import compare as cmp

PERTURBED = ("iekf", "converged", 90.0, "e_rho")


@pytest.fixture(scope="module")
def fresh(tmp_path_factory):
    """``fresh(case)`` -> percentiles.csv of the reduced case, run once per module."""
    cache = {}

    def get(case: str):
        if case not in cache:
            cache[case] = reg.run_case(case, tmp_path_factory.mktemp(f"case{case}") / "run", jobs=2)
        return cache[case]

    return get


@pytest.mark.slow
@pytest.mark.parametrize("case", list(reg.CASES))
def test_reduced_case_matches_its_golden(case, fresh):
    if not reg.config_path(case).is_file():
        pytest.skip(f"no configs/case{case}.yaml")
    golden = reg.golden_path(case)
    assert golden.is_file(), f"no golden table {golden}: run 'make goldens', review and commit it"
    res = cmp.compare_tables(cmp.load_percentiles(fresh(case)), cmp.load_percentiles(golden), reg.RTOL, reg.ATOL,
                             "both", f"case{case} (fresh run)", str(golden))  # fmt: skip
    assert res.ok, "\n" + cmp.format_comparison(res)


@pytest.mark.slow
@pytest.mark.parametrize("case", list(reg.CASES))
def test_numpy_path_matches_its_own_golden(case, tmp_path):
    """The readable reference path has its own goldens (numpy/caseX.csv; docs/outputs.md says why)."""
    if not reg.config_path(case).is_file():
        pytest.skip(f"no configs/case{case}.yaml")
    golden = reg.golden_path(case, kernels="numpy")
    assert golden.is_file(), f"no golden table {golden}: run 'make goldens', review and commit it"
    fresh = reg.run_case(case, tmp_path / "run", jobs=2, kernels="numpy")
    res = cmp.compare_tables(cmp.load_percentiles(fresh), cmp.load_percentiles(golden), reg.RTOL, reg.ATOL,
                             "both", f"case{case} (numpy path)", str(golden))  # fmt: skip
    assert res.ok, "\n" + cmp.format_comparison(res)


def perturb(src, dst, rel: float = 1e-2) -> float:
    """Copy golden ``src`` to ``dst`` with the :data:`PERTURBED` cell scaled by ``1 + rel``; return the new value."""
    df = pd.read_csv(src)
    f, pop, pct, col = PERTURBED
    i = df.index[(df["filter"] == f) & (df["population"] == pop) & (df["percentile"] == pct)][0]
    df.at[i, col] = float(df.at[i, col]) * (1 + rel)
    dst.write_text(df.to_csv(index=False, float_format="%.10g"))
    return float(df.at[i, col])


@pytest.mark.slow
def test_ci_fails_on_a_deliberately_perturbed_golden(fresh, tmp_path):
    golden = reg.golden_path("B")
    assert golden.is_file(), f"no golden table {golden}"
    goldens = tmp_path / "goldens"
    goldens.mkdir()
    new = perturb(golden, goldens / "caseB.csv")
    f, pop, pct, col = PERTURBED
    row = f"| {f} | {pop} | {pct:g} | {col} |"
    # spmc compare: the fresh run against the perturbed golden
    r = CliRunner().invoke(app, ["compare", str(fresh("B")), str(goldens / "caseB.csv")])
    assert r.exit_code == 1
    line = [ln for ln in r.output.splitlines() if ln.startswith(row)]
    assert len(line) == 1 and f"{new:.10g}" in line[0]
    assert "**FAIL**: 1 of" in r.output
    # the unperturbed golden passes
    assert CliRunner().invoke(app, ["compare", str(fresh("B")), str(golden)]).exit_code == 0
    # the CI entry point: rerun case B and check it against the perturbed golden
    out: list[str] = []
    assert reg.check("B", jobs=2, golden_dir=goldens, echo=out.append) is False
    assert row in "\n".join(out)
    shutil.copyfile(golden, goldens / "caseB.csv")
    assert reg.main(["check", "--cases", "B", "--goldens", str(goldens), "--kernels", "compiled"]) == 0


def test_check_without_a_golden_fails_without_running(tmp_path):
    out: list[str] = []
    assert reg.check("B", golden_dir=tmp_path, echo=out.append) is False
    assert "no golden table" in out[0] and "make goldens" in out[0]


def test_reduced_scenario_only_cuts_the_trials():
    from stereopose_mc.config import load_scenario

    full = load_scenario(reg.config_path("B"))
    red = reg.reduced_scenario("B")
    assert red.trials == reg.CI_TRIALS
    assert red.model_copy(update={"trials": full.trials}) == full


@pytest.mark.parametrize("text,cases", [("B", ["B"]), ("caseA,caseF", ["A", "F"]), ("bd", ["B", "D"])])
def test_parse_cases(text, cases):
    assert reg._parse_cases(text, reg.CONFIG_DIR) == cases
    with pytest.raises(SystemExit):
        reg._parse_cases("G", reg.CONFIG_DIR)
