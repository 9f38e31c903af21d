"""``spmc compare`` and ``outputs.compare``: alignment, tolerances, inf/nan, missing rows, exit codes."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from outputs.output_helpers import spmc
from stereopose_mc.outputs import compare as cmp
from stereopose_mc.rundir import percentiles, tables


def synthetic_table(seed: int = 3) -> pd.DataFrame:
    """A percentile table from random per-trial errors: two filters, 12 trials, 2 diverged for 'ekf'."""
    rng = np.random.default_rng(seed)
    rows = []
    for f in ("iekf", "ekf"):
        for t in range(12):
            div = f == "ekf" and t in (3, 7)
            e = {n: (np.nan if div else float(rng.lognormal())) for n in tables.ERROR_UNITS}
            rows.append({"trial": t, "filter": f, "diverged": div, **e})
    return percentiles.percentile_table(pd.DataFrame(rows), [50, 70, 90, 100])


def write(df: pd.DataFrame, path):
    path.write_text(df.to_csv(index=False, float_format="%.10g"))
    return path


@pytest.fixture
def base(tmp_path):
    return write(synthetic_table(), tmp_path / "base.csv")


def test_same_table_exits_0(base):
    r = spmc("compare", base, base)
    assert r.exit_code == 0, r.output
    assert "**OK**: 0 of 160 cells out of tolerance" in r.output  # 2 filters x 2 pops x 4 pcts x 10 columns


def test_perturbed_cell_exits_1_and_is_shown(base, tmp_path):
    df = pd.read_csv(base)
    i = df.index[(df["filter"] == "iekf") & (df["population"] == "converged") & (df["percentile"] == 90)][0]
    old = float(df.at[i, "e_theta"])
    df.at[i, "e_theta"] = old * (1 + 1e-5)
    pert = write(df, tmp_path / "pert.csv")
    r = spmc("compare", pert, base)
    assert r.exit_code == 1
    lines = [ln for ln in r.output.splitlines() if ln.startswith("| iekf")]
    assert len(lines) == 1
    cells = [c.strip() for c in lines[0].strip("|").split("|")]
    assert cells[:4] == ["iekf", "converged", "90", "e_theta"]
    assert float(cells[4]) == pytest.approx(old * (1 + 1e-5), rel=1e-9) and float(cells[5]) == pytest.approx(old)
    assert float(cells[7]) == pytest.approx(1e-5, rel=1e-3)
    assert "**FAIL**: 1 of 160" in r.output
    # within a looser tolerance it passes, and --all lists every cell
    assert spmc("compare", pert, base, "--rtol", "1e-4").exit_code == 0
    r = spmc("compare", pert, base, "--all")
    assert sum(ln.startswith("| iekf") or ln.startswith("| ekf") for ln in r.output.splitlines()) == 160
    # only the 'all' population: the perturbed converged cell is not compared
    assert spmc("compare", pert, base, "--population", "all").exit_code == 0


def test_atol(base, tmp_path):
    df = pd.read_csv(base)
    df.loc[0, "e_k1"] += 1e-3
    pert = write(df, tmp_path / "pert.csv")
    assert spmc("compare", pert, base).exit_code == 1
    assert spmc("compare", pert, base, "--atol", "1.1e-3").exit_code == 0
    assert spmc("compare", pert, base, "--atol", "0.9e-3").exit_code == 1


def test_inf_and_nan_rules(base, tmp_path):
    df = pd.read_csv(base)
    allrows = df[(df["filter"] == "ekf") & (df["population"] == "all")]
    assert np.isinf(allrows["e_rho"].iloc[-1])  # 2 of 12 diverged: the 100th percentile is +inf
    assert spmc("compare", base, base).exit_code == 0  # inf == inf
    d2 = df.copy()
    d2.loc[allrows.index[-1], "e_rho"] = 1e300
    r = spmc("compare", write(d2, tmp_path / "a.csv"), base)
    assert r.exit_code == 1 and "| ekf | all | 100 | e_rho | 1e+300 | inf |" in r.output
    d3 = df.copy()
    d3.loc[0, "e_omega"] = np.nan
    r = spmc("compare", write(d3, tmp_path / "b.csv"), base)
    assert r.exit_code == 1 and "nan mismatch" in r.output


def test_missing_rows_and_filters_fail(base, tmp_path):
    df = pd.read_csv(base)
    no_ekf = write(df[df["filter"] != "ekf"], tmp_path / "no_ekf.csv")
    r = spmc("compare", no_ekf, base)
    assert r.exit_code == 1
    assert "filters missing in run: ekf" in r.output and r.output.count("row missing in run") == 8
    r = spmc("compare", base, no_ekf)
    assert r.exit_code == 1 and "filters missing in baseline: ekf" in r.output
    no_row = write(df.drop(index=3), tmp_path / "no_row.csv")
    r = spmc("compare", no_row, base)
    assert r.exit_code == 1 and r.output.count("row missing in run") == 1
    no_col = write(df.drop(columns=["e_k2"]), tmp_path / "no_col.csv")
    r = spmc("compare", no_col, base)
    assert r.exit_code == 1 and "column missing in run" in r.output


def test_rows_align_by_key_not_by_order(base, tmp_path):
    df = pd.read_csv(base).sample(frac=1.0, random_state=0)
    assert spmc("compare", write(df, tmp_path / "shuffled.csv"), base).exit_code == 0


def test_run_directory_argument(run_dir):
    r = spmc("compare", run_dir, run_dir / "percentiles.csv")
    assert r.exit_code == 0, r.output


def test_input_errors_exit_2(base, tmp_path):
    r = spmc("compare", tmp_path / "nope.csv", base)
    assert r.exit_code == 2 and "no such file" in r.output
    r = spmc("compare", tmp_path, base)
    assert r.exit_code == 2 and "no percentiles.csv" in r.output
    (tmp_path / "x.csv").write_text("a,b\n1,2\n")
    r = spmc("compare", tmp_path / "x.csv", base)
    assert r.exit_code == 2 and "not a percentile table" in r.output
    dup = pd.concat([pd.read_csv(base).iloc[:2], pd.read_csv(base).iloc[:1]])
    r = spmc("compare", write(dup, tmp_path / "dup.csv"), base)
    assert r.exit_code == 2 and "more than once" in r.output
    assert spmc("compare", base, base, "--population", "some").exit_code == 2


finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(a=finite, b=finite, rtol=st.floats(0, 1e-2), atol=st.floats(0, 1e-2))
def test_cell_equal_is_the_documented_inequality(a, b, rtol, atol):
    assert cmp.cell_equal(a, b, rtol, atol) == (abs(a - b) <= atol + rtol * abs(b))
    assert cmp.cell_equal(a, a, 0.0, 0.0)


SPECIAL = [(math.inf, math.inf, True), (-math.inf, -math.inf, True), (math.inf, -math.inf, False),
           (math.inf, 1e308, False), (math.nan, math.nan, True), (math.nan, 1.0, False), (1.0, math.nan, False)]


@pytest.mark.parametrize("a,b,eq", SPECIAL)
def test_cell_equal_special_values(a, b, eq):
    assert cmp.cell_equal(a, b, 1.0, 1.0) is eq
