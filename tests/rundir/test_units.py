"""Self-describing outputs (issue 13, item 5): units in every Parquet field, integer
percentiles, scenario hash and seed in the file metadata; old tables still compare."""

from __future__ import annotations

import pandas as pd
import pyarrow.parquet as pq
import pytest

from stereopose_mc.outputs import compare as cmp
from stereopose_mc.rundir import percentiles, store, tables

from cli_helpers import run_ok, spmc

TABLES = ("trials.parquet", "timeseries.parquet", "timing.parquet", "percentiles.parquet")


@pytest.fixture(scope="module")
def run(quick_scenario, tmp_path_factory):
    out = tmp_path_factory.mktemp("u") / "run"
    run_ok("run", quick_scenario, "--out", out, "--seed", 11)
    return out


@pytest.mark.parametrize("name", TABLES)
def test_every_field_has_its_unit(run, name):
    units = store.field_units(run / name)
    missing = [c for c, u in units.items() if u is None]
    assert not missing, f"{name}: no unit for {missing}; add them to rundir.tables.COLUMN_UNITS and docs/outputs.md"
    expect = {"e_rho": "m", "e_rho_dot": "m/s", "e_omega": "deg/s", "e_theta": "deg", "t": "s", "runtime_s": "s"}
    assert {c: units[c] for c in units if c in expect} == {c: expect[c] for c in units if c in expect}


@pytest.mark.parametrize("name", TABLES)
def test_file_metadata_names_scenario_hash_and_seed(run, name):
    md = store.read_parquet_metadata(run / name)
    man = pd.read_json(run / "manifest.json", typ="series")
    assert md["stereopose_mc.seed"] == "11" and md["stereopose_mc.scenario_hash"] == man["scenario_hash"]
    assert md["stereopose_mc.table"] == name.removesuffix(".parquet")


def test_documented_units_match_the_files(run):
    """Every column row of docs/outputs.md's unit tables says what the files' field metadata says."""
    import re
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[2] / "docs" / "outputs.md").read_text(encoding="utf-8")
    files = {}
    for name in TABLES:
        files.update({c: u for c, u in store.field_units(run / name).items() if c != "percentile"})
    tables = re.findall(r"^\| column \| unit \| meaning \|\n((?:\|.*\n)+)", doc, flags=re.M)
    assert len(tables) >= 3  # trials, timeseries, timing
    checked = 0
    for names, unit in re.findall(r"^\| ((?:`\w+`(?:, )?)+) \| ([^|…]+?) \|", "".join(tables), flags=re.M):
        for col in re.findall(r"`(\w+)`", names):
            if col in files and unit.strip() not in ("as above",):
                assert files[col] == unit.strip(), (col, files[col], unit)
                checked += 1
    assert checked >= 20


def test_percentiles_are_integers(run):
    assert pq.read_schema(run / "percentiles.parquet").field("percentile").type == "int64"
    assert pd.read_parquet(run / "percentiles.parquet")["percentile"].tolist()[:4] == [50, 70, 90, 100]
    pt = percentiles.percentile_table(pd.read_parquet(run / "trials.parquet"), [50, 99.9])
    assert pt["percentile"].tolist()[:2] == [50.0, 99.9]  # a fractional request keeps floats


def test_compare_reads_old_float_percentile_tables(run, tmp_path):
    old = pd.read_parquet(run / "percentiles.parquet")
    old["percentile"] = old["percentile"].astype(float)  # as written before the percentiles became integers
    old.to_parquet(tmp_path / "old.parquet", index=False)
    res = cmp.compare_paths(run, tmp_path / "old.parquet")
    assert res.ok and len(res.cells) > 0
    r = spmc("compare", run, tmp_path / "old.parquet")
    assert r.exit_code == 0, r.output


@pytest.mark.parametrize("name", TABLES)
def test_float_columns_are_written_without_dictionary_pages(run, name):
    """``store.parquet_options``: dictionary pages only for the columns that are not floating point (a dictionary
    of nearly all-distinct floats costs time and size); zstd on the other columns, none on the floats (it took more
    than half of the writing time for 5-9 % of their size); the values read back are the table's."""
    import pyarrow.types as pat

    f = pq.ParquetFile(run / name)
    rg = f.metadata.row_group(0)
    seen_float = seen_other = 0
    for i, field in enumerate(f.schema_arrow):
        col = rg.column(i)
        has_dict = col.dictionary_page_offset is not None
        assert col.compression == ("UNCOMPRESSED" if pat.is_floating(field.type) else "ZSTD"), (name, field.name)
        if pat.is_floating(field.type):
            assert not has_dict, (name, field.name, col.encodings)
            seen_float += 1
        elif pat.is_string(field.type) or pat.is_large_string(field.type):
            assert has_dict, (name, field.name, col.encodings)
            seen_other += 1
    assert seen_float > 0


def test_parquet_options_round_trip(tmp_path):
    df = pd.DataFrame({"filter": ["iekf", "ekf"] * 50, "trial": range(100), "e": [0.1 * i for i in range(100)]})
    store.write_parquet(tmp_path / "t.parquet", df, {"k": "v"})
    back = pd.read_parquet(tmp_path / "t.parquet")
    pd.testing.assert_frame_equal(back, df)
    enc = {f.name: pq.ParquetFile(tmp_path / "t.parquet").metadata.row_group(0).column(i).dictionary_page_offset
           for i, f in enumerate(pq.ParquetFile(tmp_path / "t.parquet").schema_arrow)}  # fmt: skip
    assert enc["e"] is None and enc["filter"] is not None and enc["trial"] is not None
