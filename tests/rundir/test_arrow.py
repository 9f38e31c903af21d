"""``rundir/arrow.py`` against pyarrow's own converters; the run path's tables against pandas."""

from __future__ import annotations

import ast
import subprocess
import sys

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stereopose_mc.rundir import arrow, percentiles, store, tables

FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64)
TEXT = st.one_of(st.none(), st.text(max_size=6))


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal element by element, NaN equal to NaN and None to None, same dtype."""
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    if a.dtype.kind == "f":
        return bool(np.array_equal(a, b, equal_nan=True))
    return a.tolist() == b.tolist()


def _reference(v: np.ndarray) -> pa.Array:
    """What ``pa.Table.from_pandas`` stores for a pandas-3 column of these values."""
    return pa.array(v, type=pa.large_string() if v.dtype == object else None, from_pandas=True)


@settings(max_examples=60, deadline=None)
@given(st.lists(FLOATS, max_size=40), st.integers(0, 5), st.integers(0, 5))
def test_float_columns_match_pyarrow_both_ways_nan_as_null(values, lo, cut):
    v = np.array(values, float)
    a = arrow.to_arrow(v)
    assert a.equals(_reference(v)) and a.null_count == int(np.isnan(v).sum())
    assert _same(arrow.to_numpy(a), v)
    s = a.slice(min(lo, len(v)), cut)  # an offset into the buffers
    assert _same(arrow.to_numpy(s), v[min(lo, len(v)) : min(lo, len(v)) + cut])


@settings(max_examples=40, deadline=None)
@given(st.lists(TEXT, max_size=30), st.integers(0, 4))
def test_string_columns_match_pyarrow_both_ways_none_as_null(values, lo):
    v = np.empty(len(values), object)
    v[:] = values
    a = arrow.to_arrow(v)
    assert a.type == pa.large_string() and a.equals(_reference(v))
    assert _same(arrow.to_numpy(a), v)
    lo = min(lo, len(v))
    assert _same(arrow.to_numpy(a.slice(lo)), v[lo:])
    assert _same(arrow.to_numpy(pa.array(values, pa.string())), v)  # files may hold plain strings too


@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.int16, np.int8, np.uint8, np.float32, np.bool_])
def test_integer_and_bool_columns_match_pyarrow(dtype):
    rng = np.random.default_rng(3)
    v = (rng.random(37) < 0.4) if dtype is np.bool_ else rng.integers(-9, 9, 37).astype(dtype)
    a = arrow.to_arrow(v)
    assert a.equals(_reference(v))
    assert _same(arrow.to_numpy(a), v)
    assert _same(arrow.to_numpy(a.slice(5, 19)), v[5:24])
    chunked = pa.chunked_array([a.slice(0, 10), a.slice(10)])
    assert _same(arrow.to_numpy(chunked), v)
    assert _same(arrow.to_numpy(pa.chunked_array([], a.type)), v[:0])


def test_refusals_are_clear():
    with pytest.raises(ValueError, match="1-D"):
        arrow.to_arrow(np.zeros((2, 2)))
    with pytest.raises(TypeError, match="dtype"):
        arrow.to_arrow(np.zeros(2, "datetime64[s]"))
    with pytest.raises(ValueError, match="integer column"):
        arrow.to_numpy(pa.array([1, None], pa.int64()))


def _frame() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(5)
    n = 23
    f = rng.normal(size=n)
    f[[2, 7]] = np.nan
    reason = np.empty(n, object)
    reason[:] = ["", "nees: x", "lost: y", ""] * 5 + ["", "", ""]
    name = np.empty(n, object)
    name[:] = ["iekf", "ekf"] * 11 + ["iekf"]
    return {"trial": np.arange(n, dtype=np.int64), "filter": name, "e_rho": f, "diverged": rng.random(n) < 0.3,
            "diverged_reason": reason, "iterations": rng.integers(0, 9, n).astype(np.int16)}  # fmt: skip


def test_a_table_of_columns_is_the_parquet_file_pandas_wrote(tmp_path):
    """The same bytes as ``pa.Table.from_pandas`` (what the run path wrote before it stopped using pandas)."""

    cols = _frame()
    meta = {"stereopose_mc.table": "trials"}
    units = {"e_rho": "m", "trial": "-"}
    store.write_parquet(tmp_path / "a.parquet", cols, meta, units)
    store.write_parquet(tmp_path / "b.parquet", pd.DataFrame(cols), meta, units)
    assert (tmp_path / "a.parquet").read_bytes() == (tmp_path / "b.parquet").read_bytes()
    back = tables.columns_of(pq.ParquetFile(tmp_path / "a.parquet").read())
    assert all(_same(back[k], v) for k, v in cols.items())
    pd.testing.assert_frame_equal(pd.read_parquet(tmp_path / "a.parquet"), pd.DataFrame(cols))


def test_percentiles_csv_and_markdown_match_pandas():
    """``percentile_columns`` equals a pandas groupby reference; ``csv_text`` equals ``DataFrame.to_csv``."""
    rng = np.random.default_rng(7)
    n = 40
    cols = {"trial": np.repeat(np.arange(n // 2), 2), "filter": np.array(["iekf", "ekf"] * (n // 2), object),
            "diverged": rng.random(n) < 0.25, "diverged_reason": np.array([""] * n, object)}  # fmt: skip
    for name in tables.ERROR_NAMES:
        cols[name] = rng.lognormal(size=n)
    cols["e_k1"][3] = np.nan
    df = pd.DataFrame(cols)
    for pcts in ([50, 70, 90, 100], [50, 99.9]):
        pt = percentiles.percentile_columns(cols, pcts)
        ref = []
        for label, g in df.groupby("filter", sort=False):
            div = g["diverged"].to_numpy()
            for pop in ("all", "converged"):
                for p in pcts:
                    row = [label, pop, p]
                    for name in tables.ERROR_NAMES:
                        v = g[name].to_numpy(float)
                        v = np.where(div | ~np.isfinite(v), np.inf, v) if pop == "all" else v[~div & np.isfinite(v)]
                        row.append(np.percentile(v, p, method="inverted_cdf"))
                    # trials in the population, lost, inconsistent (no such column: 0), diverged (= lost)
                    row += [len(g) - (pop == "converged") * int(div.sum()), int(div.sum()), 0, int(div.sum())]
                    ref.append(row)
        got = list(zip(*(pt[k].tolist() for k in pt)))
        assert [list(r) for r in got] == ref
        expect = pd.DataFrame(pt).to_csv(index=False, float_format="%.10g")
        assert tables.csv_text(pt) == expect
        # the same table from a DataFrame, a pyarrow Table or columns
        assert percentiles.percentiles_markdown(pt, cols) == percentiles.percentiles_markdown(pd.DataFrame(pt), df)
        assert percentiles.percentiles_markdown(tables.arrow_table(pt), tables.arrow_table(cols)) == \
            percentiles.percentiles_markdown(pt, cols)  # fmt: skip
    assert "inf" in tables.csv_text(percentiles.percentile_columns(cols, [100]))


def test_a_run_imports_neither_pandas_nor_scipy_linalg(quick_scenario, tmp_path):
    """``spmc run`` never imports pandas (nor pyarrow.compute); with the compiled kernels not scipy.linalg
    either (``core/kernels/_blas.py``): ~0.4 s of a two-trial run (docs/performance.md)."""
    code = ("import sys, atexit\n"
            "atexit.register(lambda: print('LOADED', sorted(m for m in ('pandas', 'scipy.linalg', 'pyarrow.compute')"
            " if m in sys.modules)))\n"
            "from stereopose_mc.cli.main import main\n"
            "sys.argv = ['spmc'] + sys.argv[1:]\nmain()\n")  # fmt: skip
    for kernels, allowed in (("numpy", ["scipy.linalg"]), ("compiled", [])):  # the numpy filters use scipy.linalg
        out = tmp_path / kernels
        r = subprocess.run([sys.executable, "-c", code, "run", str(quick_scenario), "--trials", "2", "--out", str(out),
                            "--no-report", "--kernels", kernels], capture_output=True, text=True, timeout=600)  # fmt: skip
        assert r.returncode == 0, r.stderr
        loaded = r.stdout.rpartition("LOADED ")[2].strip()
        assert set(ast.literal_eval(loaded)) <= set(allowed), r.stdout[-400:]
        assert (out / "trials.parquet").is_file() and "2 trials in" in r.stdout


def test_chunk_files_merge_as_pandas_would(tmp_path):
    """``engine._merged``: concatenated and sorted by (trial, filter in the scenario's order), stably."""
    from stereopose_mc.mc import engine

    cols = _frame()
    files = []
    for i, rows in enumerate((np.arange(0, 9), np.arange(9, 23))):  # filter-major blocks, as a chunk writes them
        part = tables.take_rows(cols, rows[np.argsort(cols["filter"][rows] != "ekf", kind="stable")])
        store.write_parquet(tmp_path / f"trials-{i}.parquet", part)
        files.append(tmp_path / f"trials-{i}.parquet")
    order = {"ekf": 0, "iekf": 1}
    got = engine._merged(files, order)
    df = pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)
    df["_f"] = df["filter"].map(order)
    ref = df.sort_values(["trial", "_f"], kind="stable").drop(columns="_f").reset_index(drop=True)
    pd.testing.assert_frame_equal(pd.DataFrame(got), ref)


def test_a_run_result_reads_as_its_files(quick_scenario, tmp_path):
    """``RunResult.trials`` / ``.percentiles`` (built from the columns on first access) equal the published files."""
    from stereopose_mc.config.loader import load_scenario
    from stereopose_mc.mc import engine

    out = tmp_path / "run"
    res = engine.run(load_scenario(quick_scenario), out, engine.RunOptions(trials=3, chunk_size=2, command=["test"]))
    pd.testing.assert_frame_equal(res.trials, pd.read_parquet(out / "trials.parquet"))
    pd.testing.assert_frame_equal(res.percentiles, pd.read_parquet(out / "percentiles.parquet"))
    assert (out / "percentiles.csv").read_text() == res.percentiles.to_csv(index=False, float_format="%.10g")
