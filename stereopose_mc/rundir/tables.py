"""The run's tables as storage: column names and units, and tables as :data:`Columns`.

The run path (``spmc run``) builds, merges and writes its tables as :data:`Columns`
(name -> 1-D numpy array, in column order) and pyarrow tables, without pandas (importing
pandas alone takes ~0.25 s, a quarter of a two-trial run; ``rundir/arrow.py``). The
functions that read a table take a pandas DataFrame, a pyarrow Table or :data:`Columns`
alike (:func:`columns_of`). The rows of a chunk are built in ``mc/rows.py``, the
percentile table in ``rundir/percentiles.py``.
"""

from __future__ import annotations

import csv
import io
from typing import TYPE_CHECKING, Any, Dict

import numpy as np

from ..core import errorstate as es
from .arrow import to_arrow, to_numpy

if TYPE_CHECKING:
    import pandas as pd
    import pyarrow as pa

Columns = Dict[str, np.ndarray]  # a table as name -> 1-D array (strings: object arrays), in column order

ERROR_NAMES = ("e_rho", "e_rho_dot", "e_omega", "e_theta", "e_k1", "e_k2")  # the six errors, in this order
ERROR_UNITS = {"e_rho": "m", "e_rho_dot": "m/s", "e_omega": "deg/s", "e_theta": "deg", "e_k1": "-", "e_k2": "-"}
ERROR_LABELS = {"e_rho": "rho [m]", "e_rho_dot": "rho_dot [m/s]", "e_omega": "omega [deg/s]",
                "e_theta": "theta [deg]", "e_k1": "k1 [-]", "e_k2": "k2 [-]"}  # fmt: skip
# The unit of every column of the run's tables, written into each Parquet field's metadata
# (key "unit") and listed in docs/outputs.md; "-" = dimensionless, a count, an index, a label or a flag.
COLUMN_UNITS = {
    "trial": "-", "filter": "-", "seed": "-", **ERROR_UNITS, **{f"final_{n}": u for n, u in ERROR_UNITS.items()},
    "lost": "-", "lost_step": "-", "lost_reason": "-", "inconsistent": "-", "inconsistent_step": "-",
    "inconsistent_reason": "-", "diverged": "-", "diverged_step": "-", "diverged_reason": "-", "iterations_mean": "-",
    "iekf_unconverged_steps": "-", "nees_mean": "-", "nis_mean": "-",
    "step": "-", "t": "s", "nees": "-", "nis": "-", "nis_dof": "-", "iterations": "-", "converged": "-", "gated": "-",
    "gated_features": "-", "dropped_features": "-", "outlier_features": "-",
    "nis_ratio_mean": "-", "nis_dof_mean": "-", "final_sigma_ratio_k1": "-", "final_sigma_ratio_k2": "-",
    "nees_dof": "-", "nees_gauge_dof": "-", "inside_3sigma": "-", "runtime_s": "s", "chunk": "-", "population": "-", "percentile": "%", "trials": "-",
}  # fmt: skip
NEES_PARTS = tuple(k for k in es.nees_dof(es.BLOCK_PROBE_N) if k != "nees")  # nees_<block>, nees_gauge
COLUMN_UNITS.update({n: "-" for n in NEES_PARTS} | {f"{n}_mean": "-" for n in NEES_PARTS}
                    | {f"dof_{n}": "-" for n in NEES_PARTS})  # fmt: skip
# the per-axis error-state components of the time series (err_<c>, sigma_<c>) and their units: the attitude chart's
# d rho, d rho_dot, d omega, the attitude error vector a (theta), d k (core.errorstate; mc.trial.axis_errors)
AXES = tuple(f"{b}_{c}" for b in ("rho", "rho_dot", "omega", "theta") for c in "xyz") + ("k1", "k2")
AXIS_UNITS = {a: u for a, u in zip(AXES, ["m"] * 3 + ["m/s"] * 3 + ["deg/s"] * 3 + ["deg"] * 3 + ["-"] * 2)}
COLUMN_UNITS.update({f"{p}_{a}": u for a, u in AXIS_UNITS.items() for p in ("err", "sigma")})


def columns_of(table: Any) -> Columns:
    """A table's columns as numpy arrays: a pyarrow Table, a pandas DataFrame or :data:`Columns`."""
    if isinstance(table, dict):
        return table
    if hasattr(table, "column_names"):  # pyarrow.Table (nulls -> NaN or None)
        return {n: to_numpy(table.column(n)) for n in table.column_names}
    return {str(n): table[n].to_numpy() for n in table.columns}  # pandas.DataFrame


def concat_columns(parts: list[Columns]) -> Columns:
    """Row-wise concatenation of tables with the same columns (``pd.concat(..., ignore_index=True)``)."""
    return {n: np.concatenate([p[n] for p in parts]) for n in parts[0]}


def take_rows(cols: Columns, rows: np.ndarray) -> Columns:
    """The rows ``rows`` (indices or a boolean mask) of every column."""
    return {n: v[rows] for n, v in cols.items()}


def strings(v: Any, n: int | None = None) -> np.ndarray:
    """A column of strings as an object array (``n`` copies of one string when ``n`` is given)."""
    if n is not None:
        out = np.empty(n, object)
        out[:] = v
        return out
    return np.asarray(v, dtype=object)


def arrow_table(cols: Columns) -> pa.Table:
    """:data:`Columns` as a pyarrow Table, typed as ``pa.Table.from_pandas`` types a DataFrame of them
    under pandas 3 (strings ``large_string``, NaN stored as null), so the Parquet bytes are those
    the pandas path wrote (tested); without importing pandas (``rundir.arrow``)."""
    import pyarrow as pa

    return pa.table({n: to_arrow(v) for n, v in cols.items()})


def csv_text(cols: Columns, float_format: str = "%.10g") -> str:
    """A table as CSV text, as ``DataFrame.to_csv(index=False, float_format=...)`` writes it (tested):
    floats with ``float_format``, NaN as an empty field, minimal quoting, ``\\n`` line ends."""

    def cell(v: Any) -> Any:
        if isinstance(v, (float, np.floating)):
            return "" if np.isnan(v) else float_format % v
        return v

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(list(cols))
    for row in zip(*(v.tolist() if v.dtype != object else v for v in cols.values())):
        w.writerow([cell(v) for v in row])
    return buf.getvalue()
