"""Track tables on disk: your own tracker's output as a measurement source (``measurements.source: tracks``).

A track file is Parquet (``.parquet``) or CSV (``.csv``), one row per step and live track, with
the columns of :data:`TRACK_FILE_COLUMNS` (docs/images.md, "Your own tracks"). Pixel positions
use the camera model's continuous image coordinates (``col = c_x + f_px u``, pixel ``[i, j]``
covers ``j <= col < j + 1``; OpenCV's integer pixel centres are ``col = x_cv + 0.5``). The
table the image source writes (sim/images.py) is a valid track file, audit columns included.

Time is ``step`` (k, t = k dt), or ``t_s`` alone (then ``step = round(t_s / dt)``, which must
match ``t_s`` to ``1e-6 dt``). Per trial (a ``trial`` column, or one trial 0), the rows are in
non-decreasing time and a track id appears at most once per step.

A truth file (optional, :data:`TRUTH_FILE_COLUMNS`) gives the true relative state per step:
``step`` or ``t_s`` (or ``t``, the column of ``spmc simulate``'s truth table), ``rho_x`` ...
``q3``, optionally ``trial``.

Every problem is a :class:`TracksFileError` with a one-line message naming the file and the
column.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

REQUIRED = ("track_id", "col_r", "row_r", "col_l", "row_l")
TIME = ("step", "t_s")
TRACK_FILE_COLUMNS = {
    "trial": "int64: optional; the trial the row belongs to (default 0: one trial)",
    "step": "int64: time step k >= 0 (t = k dt); this or t_s is required",
    "t_s": "float64: time (s); this or step is required",
    "track_id": "int64: required; the track's identity, constant while it is tracked",
    "col_r": "float64: required; right-image column (px, camera-model convention: OpenCV x + 0.5), finite",
    "row_r": "float64: required; right-image row (px), finite",
    "col_l": "float64: required; left-image column (px), finite",
    "row_l": "float64: required; left-image row (px), finite",
    "dcol_r": "float64: optional; right column velocity (px/s); nan: not measured at this step",
    "drow_r": "float64: optional; right row velocity (px/s)",
    "dcol_l": "float64: optional; left column velocity (px/s)",
    "drow_l": "float64: optional; left row velocity (px/s)",
    "sigma_px": "float64: optional; the position's standard deviation (px), > 0",
    "sigma_pxps": "float64: optional; the velocity's standard deviation (px/s), > 0",
    "body_x": "float64: optional; the track's true point in the target frame T (m; nan: unknown)",
    "body_y": "float64: optional",
    "body_z": "float64: optional",
}
STATE_COLUMNS = ("rho_x", "rho_y", "rho_z", "rho_dot_x", "rho_dot_y", "rho_dot_z",
                 "omega_x", "omega_y", "omega_z", "q0", "q1", "q2", "q3")  # fmt: skip
TRUTH_FILE_COLUMNS = {
    "trial": "int64: optional; the trial (default: the same truth for every trial)",
    "step": "int64: time step k; this, t_s or t is required",
    "t_s": "float64: time (s)",
    **{c: f"float64: required; {u}" for c, u in zip(STATE_COLUMNS, ["target centre in L (m)"] * 3
       + ["its velocity in L (m/s)"] * 3 + ["target angular velocity in L (rad/s)"] * 3
       + ["attitude quaternion T -> L, scalar first"] * 4)},  # fmt: skip
}
INTEGER = ("trial", "step", "track_id")
STEP_TOL = 1e-6  # t_s must be a whole number of dt to this fraction of dt


class TracksFileError(ValueError):
    """A track or truth file that cannot be used (one line: the file, the column, what is wrong)."""


def _read(path: Path) -> pd.DataFrame:
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".parquet", ".csv"):
        raise TracksFileError(f"{path}: expected a .parquet or .csv file")
    if not path.is_file():
        raise TracksFileError(f"{path}: file not found")
    try:
        return pd.read_parquet(path) if suffix == ".parquet" else pd.read_csv(path)
    except (OSError, ValueError, pd.errors.ParserError) as exc:  # pyarrow's errors are OSError / ValueError
        raise TracksFileError(f"{path}: cannot read: {str(exc).splitlines()[0]}") from None


def _numeric(df: pd.DataFrame, path: Path, columns) -> None:
    """Columns present in ``df`` among ``columns`` are numbers (integers for :data:`INTEGER`), in place."""
    for c in columns:
        if c not in df:
            continue
        col = df[c]
        if col.dtype == bool or not pd.api.types.is_numeric_dtype(col):
            raise TracksFileError(f"{path}: column '{c}' must be numeric (got {col.dtype})")
        if c in INTEGER:
            v = col.to_numpy(dtype=float)
            bad = ~np.isfinite(v) | (v != np.round(v)) | (v < 0)
            if bad.any():
                raise TracksFileError(f"{path}: column '{c}' must hold whole numbers >= 0 (row {int(np.argmax(bad))}: "
                                      f"{col.iloc[int(np.argmax(bad))]})")  # fmt: skip
            df[c] = v.astype(np.int64)
        else:
            df[c] = col.astype(np.float64)


def _steps(df: pd.DataFrame, path: Path, dt: float | None, time_cols=TIME) -> None:
    """Adds ``step`` from ``t_s`` when only the time is given (``dt``: the scenario's step), in place."""
    if "step" in df:
        return
    t_col = next((c for c in time_cols if c in df), None)
    if t_col is None:
        raise TracksFileError(f"{path}: missing column 'step' (or '{time_cols[1]}')")
    t = df[t_col].to_numpy()
    if not np.all(np.isfinite(t)):
        raise TracksFileError(f"{path}: column '{t_col}' is not finite at row {int(np.argmax(~np.isfinite(t)))}")
    if dt is None:
        raise TracksFileError(f"{path}: column '{t_col}' without 'step' needs the scenario's dt to number the steps")
    k = np.round(t / dt)
    off = np.abs(t - k * dt) > STEP_TOL * dt
    if off.any() or (k < 0).any():
        i = int(np.argmax(off | (k < 0)))
        raise TracksFileError(f"{path}: column '{t_col}' is not a whole number of dt = {dt:g} s >= 0 at row {i} "
                              f"({t[i]:g})")  # fmt: skip
    df.insert(0, "step", k.astype(np.int64))


def _monotonic(df: pd.DataFrame, path: Path) -> None:
    """Per trial, rows in non-decreasing ``step`` (and ``t_s`` increasing with it)."""
    for trial, g in df.groupby("trial", sort=False):
        k = g["step"].to_numpy()
        back = np.flatnonzero(np.diff(k) < 0)
        if back.size:
            i = int(g.index[back[0] + 1])
            raise TracksFileError(f"{path}: column 'step' goes back in time at row {i} ({k[back[0]]} -> "
                                  f"{k[back[0] + 1]}, trial {trial}); sort the rows by time")  # fmt: skip
        if "t_s" in g:
            t = g["t_s"].to_numpy()
            d_t, d_k = np.diff(t), np.diff(k)
            bad = np.flatnonzero(((d_k > 0) & ~(d_t > 0)) | ((d_k == 0) & (d_t != 0)))
            if bad.size:
                i = int(g.index[bad[0] + 1])
                raise TracksFileError(f"{path}: column 't_s' does not increase with 'step' at row {i} (trial {trial})")


def read_tracks(path, dt: float | None = None) -> pd.DataFrame:
    """A validated track table: the file's columns (integers as int64, numbers as float64), with ``trial``
    (0 when absent) and ``step`` (from ``t_s`` and ``dt`` when absent), rows in the file's order."""
    path = Path(path)
    df = _read(path)
    for c in REQUIRED:
        if c not in df:
            raise TracksFileError(f"{path}: missing column '{c}' (required: {', '.join(REQUIRED)} and step or t_s)")
    _numeric(df, path, [c for c in TRACK_FILE_COLUMNS if c in df])
    _steps(df, path, dt)
    if "trial" not in df:
        df.insert(0, "trial", np.zeros(len(df), np.int64))
    for c in REQUIRED[1:]:
        v = df[c].to_numpy()
        if not np.all(np.isfinite(v)):
            raise TracksFileError(f"{path}: column '{c}' is not finite at row {int(np.argmax(~np.isfinite(v)))}")
    for c in ("sigma_px", "sigma_pxps"):
        if c in df and not np.all(df[c].to_numpy() > 0):
            raise TracksFileError(f"{path}: column '{c}' must be > 0 (row {int(np.argmax(~(df[c].to_numpy() > 0)))})")
    dup = df.duplicated(["trial", "step", "track_id"])
    if dup.any():
        i = int(dup.idxmax())
        tid, k, trial = (int(df[c].iloc[i]) for c in ("track_id", "step", "trial"))
        raise TracksFileError(f"{path}: column 'track_id': track {tid} appears twice at step {k} (trial {trial}, "
                              f"row {i})")  # fmt: skip
    _monotonic(df, path)
    return df.reset_index(drop=True)


def read_truth(path, dt: float | None = None) -> pd.DataFrame:
    """A validated truth table: ``step`` (from ``t_s`` or ``t`` and ``dt`` when absent), the state columns,
    ``trial`` if the file has one; one row per (trial, step)."""
    path = Path(path)
    df = _read(path)
    if "t_s" not in df and "t" in df:
        df = df.rename(columns={"t": "t_s"})
    for c in STATE_COLUMNS:
        if c not in df:
            raise TracksFileError(f"{path}: missing column '{c}' (required: {', '.join(STATE_COLUMNS)} and step or t_s)")
    _numeric(df, path, [c for c in ("trial", "step", "t_s", *STATE_COLUMNS) if c in df])
    _steps(df, path, dt)
    for c in STATE_COLUMNS:
        v = df[c].to_numpy()
        if not np.all(np.isfinite(v)):
            raise TracksFileError(f"{path}: column '{c}' is not finite at row {int(np.argmax(~np.isfinite(v)))}")
    keys = ["trial", "step"] if "trial" in df else ["step"]
    dup = df.duplicated(keys)
    if dup.any():
        i = int(dup.idxmax())
        raise TracksFileError(f"{path}: column 'step': step {int(df['step'].iloc[i])} appears twice"
                              + (f" (trial {int(df['trial'].iloc[i])})" if "trial" in df else ""))  # fmt: skip
    return df.sort_values(keys, kind="stable").reset_index(drop=True)


def write_tracks(df: pd.DataFrame, path) -> Path:
    """Write a track table as Parquet or CSV (by the suffix; CSV floats round-trip exactly), atomically (a
    temporary file in the same folder, then renamed: never half a file); what :func:`read_tracks` reads back."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".parquet", ".csv"):
        raise TracksFileError(f"{path}: expected a .parquet or .csv file")
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=suffix)
    os.close(fd)
    try:
        if suffix == ".parquet":
            df.to_parquet(tmp, index=False)
        else:
            df.to_csv(tmp, index=False, float_format="%.17g")
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)
    return path
