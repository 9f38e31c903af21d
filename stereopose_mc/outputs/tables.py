"""Result tables: per-trial rows, time series, percentile tables.

Percentiles use numpy's ``inverted_cdf`` method, which always returns the value of an
actual trial. Diverged trials are handled twice: in the ``all`` population their
errors count as ``+inf`` (so a high percentile shows that some trials were lost), in
the ``converged`` population they are left out and counted in ``diverged``.

The run path (``spmc run``) builds, merges and writes its tables as :data:`Columns`
(name -> 1-D numpy array, in column order) and pyarrow tables, without pandas (importing
pandas alone takes ~0.25 s, a quarter of a two-trial run; ``outputs/arrow.py``). The
functions that read a table take a pandas DataFrame, a pyarrow Table or :data:`Columns`
alike (:func:`columns_of`); :func:`percentile_table` returns a DataFrame for the report
and the studies.
"""

from __future__ import annotations

import csv
import io
import math
from typing import TYPE_CHECKING, Any, Dict

import numpy as np

from ..core import errorstate as es
from ..mc.trial import ERROR_NAMES, ChunkResult

if TYPE_CHECKING:
    import pandas as pd
    import pyarrow as pa

Columns = Dict[str, np.ndarray]  # a table as name -> 1-D array (strings: object arrays), in column order

ERROR_UNITS = {"e_rho": "m", "e_rho_dot": "m/s", "e_omega": "deg/s", "e_theta": "deg", "e_k1": "-", "e_k2": "-"}
ERROR_LABELS = {"e_rho": "rho [m]", "e_rho_dot": "rho_dot [m/s]", "e_omega": "omega [deg/s]",
                "e_theta": "theta [deg]", "e_k1": "k1 [-]", "e_k2": "k2 [-]"}  # fmt: skip
# The unit of every column of the run's tables, written into each Parquet field's metadata
# (key "unit") and listed in docs/outputs.md; "-" = dimensionless, a count, an index, a label or a flag.
COLUMN_UNITS = {
    "trial": "-", "filter": "-", "seed": "-", **ERROR_UNITS, **{f"final_{n}": u for n, u in ERROR_UNITS.items()},
    "diverged": "-", "diverged_step": "-", "diverged_reason": "-", "iterations_mean": "-",
    "iekf_unconverged_steps": "-", "nees_mean": "-", "nis_mean": "-",
    "step": "-", "t": "s", "nees": "-", "nis": "-", "nis_dof": "-", "iterations": "-", "converged": "-", "gated": "-",
    "gated_features": "-", "dropped_features": "-", "outlier_features": "-",
    "nis_ratio_mean": "-", "nis_dof_mean": "-", "final_sigma_ratio_k1": "-", "final_sigma_ratio_k2": "-",
    "runtime_s": "s", "chunk": "-", "population": "-", "percentile": "%", "trials": "-",
}  # fmt: skip
NEES_PARTS = tuple(k for k in es.nees_dof(es.BLOCK_PROBE_N) if k != "nees")  # nees_<block>, nees_gauge
COLUMN_UNITS.update({n: "-" for n in NEES_PARTS} | {f"{n}_mean": "-" for n in NEES_PARTS})
TS_COLUMNS = ["trial", "filter", "step", "t", *ERROR_NAMES, "nees", "nis", "nis_dof", "iterations", "converged",
              "gated", *NEES_PARTS]  # fmt: skip


def window_mask(t: np.ndarray, start: float) -> np.ndarray:
    return t >= start - 1e-9


def row_nanmean(a: np.ndarray) -> np.ndarray:
    """Mean over the last axis ignoring NaN (NaN for an all-NaN row), row by row.

    Each row is reduced on its own as a contiguous 1-D array (its values without the NaN),
    so the result of a trial does not depend on how many trials share the array (numpy sums
    contiguous and strided axes in different orders, which changes the last bits). The rows
    without NaN are reduced together, along the contiguous last axis of a C-ordered array:
    numpy's pairwise sum of each row, the same bits as one row at a time (tested), without a
    Python call per row.
    """
    flat = np.ascontiguousarray(a, dtype=float).reshape(math.prod(a.shape[:-1]), a.shape[-1])  # (no -1: width 0)
    out = np.full(flat.shape[0], np.nan)
    nan = np.isnan(flat)
    whole = ~nan.any(axis=-1)
    if flat.shape[-1] and whole.any():
        out[whole] = np.ascontiguousarray(flat[whole]).mean(axis=-1)
    for i in np.flatnonzero(~whole):
        v = flat[i][~nan[i]]
        if v.size:
            out[i] = v.mean()
    return out.reshape(a.shape[:-1])


def columns_of(table: Any) -> Columns:
    """A table's columns as numpy arrays: a pyarrow Table, a pandas DataFrame or :data:`Columns`."""
    if isinstance(table, dict):
        return table
    if hasattr(table, "column_names"):  # pyarrow.Table (nulls -> NaN or None)
        from .arrow import to_numpy

        return {n: to_numpy(table.column(n)) for n in table.column_names}
    return {str(n): table[n].to_numpy() for n in table.columns}  # pandas.DataFrame


def concat_columns(parts: list[Columns]) -> Columns:
    """Row-wise concatenation of tables with the same columns (``pd.concat(..., ignore_index=True)``)."""
    return {n: np.concatenate([p[n] for p in parts]) for n in parts[0]}


def take_rows(cols: Columns, rows: np.ndarray) -> Columns:
    """The rows ``rows`` (indices or a boolean mask) of every column."""
    return {n: v[rows] for n, v in cols.items()}


def _strings(v: Any, n: int | None = None) -> np.ndarray:
    """A column of strings as an object array (``n`` copies of one string when ``n`` is given)."""
    if n is not None:
        out = np.empty(n, object)
        out[:] = v
        return out
    return np.asarray(v, dtype=object)


def arrow_table(cols: Columns) -> pa.Table:
    """:data:`Columns` as a pyarrow Table, typed as ``pa.Table.from_pandas`` types a DataFrame of them
    under pandas 3 (strings ``large_string``, NaN stored as null), so the Parquet bytes are those
    the pandas path wrote (tested); without importing pandas (``outputs.arrow``)."""
    import pyarrow as pa

    from .arrow import to_arrow

    return pa.table({n: to_arrow(v) for n, v in cols.items()})


def trials_columns(chunk: ChunkResult, t: np.ndarray, window_start: float, seed: int) -> Columns:
    """One row per filter x trial, filter-major (deterministic columns only; timing is separate)."""
    w = window_mask(t, window_start)
    frames = []
    for r in chunk.runs:
        B = len(chunk.trials)
        div = r.diverged_step >= 0
        means = row_nanmean(np.moveaxis(r.errors[:, w], 1, -1))
        it_mean = row_nanmean(np.where(r.iterations[:, 1:] > 0, r.iterations[:, 1:], np.nan))
        nees_mean = row_nanmean(r.nees[:, w])
        nis_mean = row_nanmean(r.nis[:, w])
        means[div] = np.nan
        final = r.errors[:, -1]
        d = {"trial": chunk.trials.astype(np.int64), "filter": _strings(r.label, B), "seed": np.full(B, seed, np.int64)}
        for j, name in enumerate(ERROR_NAMES):
            d[name] = means[:, j]
        for j, name in enumerate(ERROR_NAMES):
            d[f"final_{name}"] = final[:, j]
        d["diverged"] = div
        d["diverged_step"] = r.diverged_step.astype(np.int64)
        d["diverged_reason"] = _strings(r.diverged_reason)
        d["iterations_mean"] = it_mean
        d["iekf_unconverged_steps"] = np.sum((r.iterations[:, 1:] > 0) & ~r.converged[:, 1:], axis=1).astype(np.int64)
        d["nees_mean"] = nees_mean
        d["nis_mean"] = nis_mean
        d.update(_fault_columns(chunk, r))
        dof = np.broadcast_to(r.nis_dof if r.dof is None else r.dof, r.nis.shape)  # per trial and step
        with np.errstate(all="ignore"):
            d["nis_ratio_mean"] = row_nanmean(np.where(dof > 0, r.nis / np.maximum(dof, 1), np.nan)[:, w])
        d["nis_dof_mean"] = dof[:, w].mean(axis=1).astype(float)
        for j, name in enumerate(("k1", "k2")):
            d[f"final_sigma_ratio_{name}"] = (r.k_sigma_ratio[:, j] if r.k_sigma_ratio is not None
                                               else np.full(B, np.nan))  # fmt: skip
        for name in NEES_PARTS:
            d[f"{name}_mean"] = row_nanmean(r.nees_parts[name][:, w]) if name in r.nees_parts else np.full(B, np.nan)
        frames.append(d)
    return concat_columns(frames)


def _fault_columns(chunk: ChunkResult, r) -> dict[str, np.ndarray]:
    """Per trial: features rejected by the filter's gate, and the tracker's dropouts and outliers (steps >= 1)."""
    B = len(chunk.trials)
    gated = np.zeros(B, np.int64) if r.gated is None else r.gated[:, 1:].sum(axis=1).astype(np.int64)
    f = chunk.faults
    drop = np.zeros(B, np.int64) if f is None else (~f.kept[:, 1:]).sum(axis=(1, 2)).astype(np.int64)
    out = np.zeros(B, np.int64) if f is None else f.outlier[:, 1:].sum(axis=(1, 2)).astype(np.int64)
    return {"gated_features": gated, "dropped_features": drop, "outlier_features": out}


def timing_columns(chunk: ChunkResult, chunk_id: int) -> Columns:
    B = len(chunk.trials)
    return concat_columns([{"trial": chunk.trials.astype(np.int64), "filter": _strings(r.label, B),
                            "runtime_s": np.asarray(r.runtime_s, float), "chunk": np.full(B, chunk_id, np.int64)}
                           for r in chunk.runs])  # fmt: skip


def timeseries_columns(chunk: ChunkResult, t: np.ndarray, keep: np.ndarray | None = None) -> Columns | None:
    """Per trial, filter and step: the six errors, NEES, NIS, IEKF iterations (filter-major; None: no rows)."""
    frames = []
    sel = np.ones(len(chunk.trials), bool) if keep is None else keep
    B = int(sel.sum())
    K1 = t.size
    if B == 0:
        return None
    for r in chunk.runs:
        d = {
            "trial": np.repeat(chunk.trials[sel].astype(np.int64), K1),
            "filter": _strings(r.label, B * K1),
            "step": np.tile(np.arange(K1, dtype=np.int32), B),
            "t": np.tile(t, B),
        }
        for j, name in enumerate(ERROR_NAMES):
            d[name] = r.errors[sel, :, j].reshape(-1)
        d["nees"] = r.nees[sel].reshape(-1)
        d["nis"] = r.nis[sel].reshape(-1)
        dof = r.nis_dof if r.dof is None else r.dof  # (K+1,) shared, or (B, K+1) per trial
        d["nis_dof"] = (np.tile(dof, B) if dof.ndim == 1 else dof[sel].reshape(-1)).astype(np.int16)
        d["iterations"] = r.iterations[sel].reshape(-1).astype(np.int16)
        d["converged"] = r.converged[sel].reshape(-1)
        d["gated"] = (np.zeros(B * K1) if r.gated is None else r.gated[sel].reshape(-1)).astype(np.int16)
        for name in NEES_PARTS:
            d[name] = r.nees_parts[name][sel].reshape(-1) if name in r.nees_parts else np.full(B * K1, np.nan)
        frames.append(d)
    return concat_columns(frames)


def pct_value(p: float, percentiles: list[float]) -> int | float:
    """Percentiles are integers (50, 70, ...) unless the scenario asks for a fractional one (99.9)."""
    return int(p) if all(float(q).is_integer() for q in percentiles) else float(p)


def percentile_columns(trials: Any, percentiles: list[float]) -> Columns:
    """Percentiles of the per-trial window means, per filter (in order of appearance) and population."""
    c = columns_of(trials)
    filt = c["filter"]
    rows: dict[str, list] = {k: [] for k in ("filter", "population", "percentile", *ERROR_NAMES, "trials", "diverged")}
    for label in dict.fromkeys(filt.tolist()):
        g = filt == label
        div = c["diverged"][g].astype(bool)
        n, nd = int(g.sum()), int(div.sum())
        for pop in ("all", "converged"):
            vals = {}
            for name in ERROR_NAMES:
                v = c[name][g].astype(float)
                vals[name] = np.where(div | ~np.isfinite(v), np.inf, v) if pop == "all" else v[~div & np.isfinite(v)]
            for p in percentiles:
                rows["filter"].append(label)
                rows["population"].append(pop)
                rows["percentile"].append(pct_value(p, percentiles))
                for name in ERROR_NAMES:
                    v = vals[name]
                    rows[name].append(float(np.percentile(v, p, method="inverted_cdf")) if v.size else np.nan)
                rows["trials"].append(n if pop == "all" else n - nd)
                rows["diverged"].append(nd)
    integral = all(float(q).is_integer() for q in percentiles)
    out: Columns = {"filter": _strings(rows["filter"]), "population": _strings(rows["population"]),
                    "percentile": np.asarray(rows["percentile"], np.int64 if integral else float)}  # fmt: skip
    out.update({name: np.asarray(rows[name], float) for name in ERROR_NAMES})
    out.update(trials=np.asarray(rows["trials"], np.int64), diverged=np.asarray(rows["diverged"], np.int64))
    return out


def percentile_table(trials: Any, percentiles: list[float]) -> pd.DataFrame:
    """:func:`percentile_columns` as a DataFrame (for the report, the studies and the docs)."""
    import pandas as pd

    return pd.DataFrame(percentile_columns(trials, percentiles))


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


def _fmt(v: float) -> str:
    if not np.isfinite(v):
        return "inf" if v > 0 else "nan"
    return f"{v:.3g}"


def format_table(pt: Any, label: str, population: str = "converged", markdown: bool = False) -> str:
    """The thesis's layout: rows 50/70/90/100, columns rho, rho_dot, omega, theta, k1, k2."""
    c = columns_of(pt)
    g = take_rows(c, (c["filter"] == label) & (c["population"] == population))
    head = ["pct"] + [ERROR_LABELS[n] for n in ERROR_NAMES]
    body = [[f"{p:g}"] + [_fmt(g[n][i]) for n in ERROR_NAMES] for i, p in enumerate(g["percentile"].tolist())]
    if markdown:
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(b) + " |" for b in body]
        return "\n".join(lines)
    widths = [max(len(x[i]) for x in [head] + body) for i in range(len(head))]
    fmt = lambda row: "  ".join(c.rjust(w) for c, w in zip(row, widths))  # noqa: E731
    return "\n".join([fmt(head), *map(fmt, body)])


UNOBSERVABLE_RATIO = 0.5  # final / initial sigma of a parameter above which the data did not reveal it


def not_observable(trials: Any, label: str) -> dict[str, float]:
    """Parameters (k1, k2) the converged trials of ``label`` carry at more than half their initial sigma.

    Maps each to its median final / initial standard deviation: the data did not reveal
    it, and (the trial being converged, so its error is within ``sigma_ratio`` of its own
    sigma) the filter says so honestly; it is not a failure.
    """
    c = columns_of(trials)
    g = (c["filter"] == label) & ~c["diverged"].astype(bool)
    out = {}
    for name in ("k1", "k2"):
        col = f"final_sigma_ratio_{name}"
        v = c[col][g].astype(float) if col in c else np.empty(0)
        v = v[~np.isnan(v)]
        if v.size and float(np.median(v)) > UNOBSERVABLE_RATIO:
            out[name] = float(np.median(v))
    return out


def population_note(trials: Any, label: str) -> str:
    """Which trials the two populations hold: the ids left out of ``converged``, by reason."""
    c = columns_of(trials)
    g = (c["filter"] == label) & c["diverged"].astype(bool)
    if not g.any():
        return "Both populations hold every trial.\n"
    by: dict[str, list[int]] = {}
    for trial, reason in zip(c["trial"][g].tolist(), c["diverged_reason"][g]):
        by.setdefault(str(reason).split(":")[0], []).append(int(trial))
    lines = ["`converged` leaves out these trials (`all` holds them as +inf):\n"]
    for reason in sorted(by):
        ids = sorted(by[reason])
        shown = ", ".join(map(str, ids[:30])) + (f", ... ({len(ids) - 30} more)" if len(ids) > 30 else "")
        lines.append(f"- {reason} ({len(ids)}): {shown}")
    return "\n".join(lines) + "\n"


def percentiles_markdown(pt: Any, trials: Any = None) -> str:
    c = columns_of(pt)
    out = []
    for label in dict.fromkeys(c["filter"].tolist()):
        i = int(np.flatnonzero(c["filter"] == label)[0])
        n, nd = int(c["trials"][i]), int(c["diverged"][i])
        out.append(f"## {label}: {n - nd} of {n} trials converged ({nd} diverged)\n")
        if trials is not None:
            out.append(population_note(trials, label))
            for name, m in not_observable(trials, label).items():
                out.append(f"{name}: not observable in this run (median final sigma = {m:.2f} x the initial one; "
                           "carried with its covariance, not a failure).\n")
        out.append("Converged trials only:\n\n" + format_table(c, label, "converged", markdown=True) + "\n")
        out.append("All trials (a diverged trial counts as +inf):\n\n" + format_table(c, label, "all", markdown=True) + "\n")
    return "\n".join(out)
