"""A run's tables as DataFrames with their units, and exports for other tools (``spmc export``).

Every Parquet field of a run carries its unit in its metadata (key ``unit``, docs/outputs.md);
:func:`read_table` returns a table as a pandas DataFrame with those units in
``df.attrs["units"]`` (column -> unit; ``""`` where a field has none).

:func:`export_run` writes chosen tables of a run directory in one format:

- ``csv``: ``<table>.csv`` (one header row of column names, values at full precision) and a
  units sidecar ``<table>.units.csv`` (columns ``column,unit``), so the data file stays a plain
  table for ``pandas.read_csv`` or MATLAB's ``readtable``;
- ``mat``: one MATLAB file ``<run>.mat`` (scipy.io.savemat, v5, compressed) holding one struct
  per table, with one column vector per column (text columns as cell arrays of char),
  ``units`` (a struct: column -> unit) and ``columns`` (the column order), and a ``run`` struct
  (name, seed, trials, filters, the resolved scenario as YAML text);
- ``parquet``: the run's own Parquet files, byte for byte (units and metadata included).

Every file is written to a temporary sibling and renamed; nothing is written when a
destination exists (unless ``overwrite``) or when any table is missing.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pandas as pd

from ..rundir.store import atomic_write_bytes, field_units

TABLES = ("trials", "timeseries", "percentiles", "timing")
FORMATS = ("csv", "mat", "parquet")


class ExportError(Exception):
    """An export that cannot be done as asked (not a run, a missing table, a destination in the way)."""


def read_table(run_dir: Path, name: str) -> pd.DataFrame:
    """``<run_dir>/<name>.parquet`` as a DataFrame; ``attrs``: ``units`` (column -> unit), ``table``, ``path``."""
    path = Path(run_dir) / f"{name}.parquet"
    if not path.is_file():
        raise ExportError(f"{run_dir}: no {path.name}" + (" (the run was made with timeseries 'none')"
                                                          if name == "timeseries" else ""))  # fmt: skip
    return read_parquet(path, name)


def read_parquet(path: Path, table: str) -> pd.DataFrame:
    """A Parquet file of a run as a DataFrame with ``attrs`` ``units``, ``table`` and ``path``."""
    df = pd.read_parquet(path)
    units = field_units(path)
    df.attrs.update(units={c: units.get(c) or "" for c in df.columns}, table=table, path=str(path))
    return df


def units_frame(df: pd.DataFrame) -> pd.DataFrame:
    """The ``column,unit`` table of a DataFrame read by :func:`read_table`."""
    units = df.attrs.get("units", {})
    return pd.DataFrame({"column": list(df.columns), "unit": [units.get(c, "") for c in df.columns]})


def _mat_column(s: pd.Series) -> np.ndarray:
    """A column for savemat: numbers and flags as they are, anything else as text (a cell array)."""
    if pd.api.types.is_bool_dtype(s) or pd.api.types.is_numeric_dtype(s):
        return s.to_numpy()
    return np.array(["" if v is None or (isinstance(v, float) and np.isnan(v)) else str(v) for v in s], dtype=object)


def mat_struct(df: pd.DataFrame) -> dict:
    """One table as a MATLAB struct: a field per column, ``units`` and ``columns``."""
    clash = {"units", "columns"} & set(df.columns)
    if clash:
        raise ExportError(f"table {df.attrs.get('table', '?')}: column {sorted(clash)[0]!r} clashes with a struct field")
    units = df.attrs.get("units", {})
    out = {c: _mat_column(df[c]) for c in df.columns}
    out["units"] = {c: units.get(c, "") for c in df.columns}
    out["columns"] = np.array(list(df.columns), dtype=object)
    return out


def _run_struct(run_dir: Path) -> dict:
    manifest = json.loads((run_dir / "manifest.json").read_text())
    config = (run_dir / "config.yaml").read_text() if (run_dir / "config.yaml").is_file() else ""
    return {"name": str(manifest.get("scenario", run_dir.name)), "seed": int(manifest.get("seed", 0)),
            "trials": int(manifest.get("trials", 0)), "filters": np.array(manifest.get("filters", []), dtype=object),
            "version": str(manifest.get("version", "")), "config_yaml": config}  # fmt: skip


def _mat_bytes(run_dir: Path, frames: dict[str, pd.DataFrame]) -> bytes:
    from scipy.io import savemat

    buf = io.BytesIO()
    mdict = {name: mat_struct(df) for name, df in frames.items()}
    mdict["run"] = _run_struct(run_dir)
    savemat(buf, mdict, do_compression=True, long_field_names=True, oned_as="column")
    return buf.getvalue()


def _payloads(run_dir: Path, fmt: str, tables: list[str], out: Path) -> dict[Path, bytes]:
    if fmt == "parquet":
        return {out / f"{t}.parquet": (run_dir / f"{t}.parquet").read_bytes() for t in tables}
    frames = {t: read_table(run_dir, t) for t in tables}
    if fmt == "mat":
        return {out / f"{run_dir.resolve().name}.mat": _mat_bytes(run_dir, frames)}
    files = {}
    for t, df in frames.items():
        files[out / f"{t}.csv"] = df.to_csv(index=False).encode()
        files[out / f"{t}.units.csv"] = units_frame(df).to_csv(index=False).encode()
    return files


def present_tables(run_dir: Path) -> list[str]:
    """The tables of :data:`TABLES` that a run directory holds."""
    return [t for t in TABLES if (Path(run_dir) / f"{t}.parquet").is_file()]


def export_run(run_dir: Path, fmt: str, tables: list[str] | None = None, out: Path | None = None,
               overwrite: bool = False) -> list[Path]:  # fmt: skip
    """Write ``tables`` (default: every table the run has) of ``run_dir`` as ``fmt`` into ``out``
    (default ``<run_dir>/export``); return the files written.

    Raises :class:`ExportError` (one line) before anything is written: not a run directory, an
    unknown format or table, a missing table, ``out`` a file, a destination that exists.
    """
    run_dir = Path(run_dir)
    if fmt not in FORMATS:
        raise ExportError(f"--format must be one of {', '.join(FORMATS)} (got {fmt!r})")
    try:
        manifest = json.loads((run_dir / "manifest.json").read_bytes())
    except (OSError, ValueError):  # (ValueError: not JSON, or not UTF-8)
        manifest = None
    if not isinstance(manifest, dict) or manifest.get("kind") != "run":
        raise ExportError(f"{run_dir}: not a run directory (no manifest.json of a run made by 'spmc run')")
    tables = list(tables) if tables else present_tables(run_dir)
    unknown = [t for t in tables if t not in TABLES]
    if unknown:
        raise ExportError(f"--tables: unknown table {unknown[0]!r} (expected some of {', '.join(TABLES)})")
    missing = [t for t in tables if not (run_dir / f"{t}.parquet").is_file()]
    if missing:
        raise ExportError(f"{run_dir}: no {missing[0]}.parquet (an unfinished run, or a table it does not write)")
    tables = list(dict.fromkeys(tables))
    out = Path(out) if out is not None else run_dir / "export"
    if out.exists() and not out.is_dir():
        raise ExportError(f"--out {out} exists and is not a directory")
    files = _payloads(run_dir, fmt, tables, out)
    taken = [p for p in files if p.exists()]
    if taken and not overwrite:
        raise ExportError(f"{taken[0]} already exists; pass --overwrite to replace it")
    try:
        out.mkdir(parents=True, exist_ok=True)
        for path, data in files.items():
            atomic_write_bytes(path, data)
    except OSError as exc:
        raise ExportError(f"--out {out}: cannot write it ({exc.strerror or exc})") from None
    return list(files)
