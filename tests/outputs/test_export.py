"""``spmc export`` / ``api.export``: CSV with units sidecars, MATLAB .mat through scipy.io, Parquet copies."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from scipy.io import loadmat

from stereopose_mc import api

from cli_helpers import SHORT, one_error_line, spmc
from scenarios import scenario_dict


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return api.run(api.from_dict(scenario_dict(trials=2, time=SHORT)), out=tmp_path_factory.mktemp("exp") / "r2").path


def _units(path):
    return {f.name: f.metadata[b"unit"].decode() for f in pq.read_schema(path)}


def test_mat_round_trips_through_loadmat(run_dir, tmp_path):
    written = api.export(run_dir, "mat", out=tmp_path)
    assert written == [tmp_path / "r2.mat"]
    m = loadmat(written[0], simplify_cells=True)
    assert {"trials", "timeseries", "percentiles", "timing", "run"} <= set(m)
    for table in ("trials", "timeseries", "percentiles"):
        want = pq.read_table(run_dir / f"{table}.parquet").to_pandas()
        s = m[table]
        assert list(s["columns"]) == list(want.columns)
        assert s["units"] == _units(run_dir / f"{table}.parquet")
        for c in want.columns:
            got = np.atleast_1d(s[c])
            if want[c].dtype.kind in "fiub":
                np.testing.assert_array_equal(got.astype(float), want[c].to_numpy(float), err_msg=c)
            else:
                text = ["" if np.size(v) == 0 else str(v) for v in got]  # loadmat gives '' (0x0 char) as []
                assert text == ["" if v is None else str(v) for v in want[c]], c
    assert m["run"]["name"] == "caseB" and m["run"]["trials"] == 2 and list(m["run"]["filters"]) == ["iekf", "ekf"]
    assert "camera:" in m["run"]["config_yaml"]


def test_csv_and_units_sidecar(run_dir, tmp_path):
    r = spmc("export", run_dir, "--format", "csv", "--tables", "trials,timeseries", "--out", tmp_path)
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["timeseries.csv", "timeseries.units.csv", "trials.csv",
                                                          "trials.units.csv"]  # fmt: skip
    for table in ("trials", "timeseries"):
        got = pd.read_csv(tmp_path / f"{table}.csv")
        want = pq.read_table(run_dir / f"{table}.parquet").to_pandas()
        assert list(got.columns) == list(want.columns)
        for c in want.columns:
            if want[c].dtype.kind == "f":
                np.testing.assert_array_equal(got[c].to_numpy(float), want[c].to_numpy(), err_msg=c)  # full precision
        units = pd.read_csv(tmp_path / f"{table}.units.csv", keep_default_na=False)
        assert dict(zip(units["column"], units["unit"])) == _units(run_dir / f"{table}.parquet")


def test_parquet_export_is_the_run_files(run_dir, tmp_path):
    api.export(run_dir, "parquet", ["percentiles"], tmp_path)
    assert (tmp_path / "percentiles.parquet").read_bytes() == (run_dir / "percentiles.parquet").read_bytes()


def test_default_out_and_overwrite(run_dir):
    first = api.export(run_dir, "csv", ["percentiles"])
    assert first[0] == run_dir / "export" / "percentiles.csv"
    before = first[0].read_bytes()
    r = spmc("export", run_dir, "--format", "csv", "--tables", "percentiles")
    one_error_line(r, "percentiles.csv already exists", "--overwrite")
    r = spmc("export", run_dir, "--format", "csv", "--tables", "percentiles", "--overwrite")
    assert r.exit_code == 0, r.output
    assert first[0].read_bytes() == before
    assert not [p for p in (run_dir / "export").iterdir() if p.name.endswith(".tmp")]  # no temporaries left


@pytest.mark.parametrize("args,needles", [
    (["--format", "xlsx"], ["--format must be one of csv, mat, parquet"]),
    (["--format", "csv", "--tables", "trials,nope"], ["unknown table 'nope'"]),
    (["--format", "csv", "--tables", ","], ["--tables"]),
])  # fmt: skip
def test_bad_input_is_one_line_exit_2_nothing_written(run_dir, tmp_path, args, needles):
    out = tmp_path / "x"
    one_error_line(spmc("export", run_dir, *args, "--out", out), *needles)
    assert not out.exists()


def test_not_a_run_and_out_onto_a_file(run_dir, tmp_path):
    one_error_line(spmc("export", tmp_path, "--format", "mat"), "not a run directory")
    f = tmp_path / "file"
    f.write_text("x")
    one_error_line(spmc("export", run_dir, "--format", "mat", "--out", f), "is not a directory")


def test_missing_table_is_named(run_dir, tmp_path):
    r = api.run(api.from_dict(scenario_dict(trials=2, time=SHORT)), out=tmp_path / "nots", timeseries="none")
    one_error_line(spmc("export", r.path, "--format", "csv", "--tables", "timeseries", "--out", tmp_path / "o"),
                   "no timeseries.parquet")  # fmt: skip
    assert sorted(p.name for p in api.export(r.path, "csv", out=tmp_path / "o")) == sorted(
        f"{t}{s}" for t in ("trials", "percentiles", "timing") for s in (".csv", ".units.csv"))  # fmt: skip
