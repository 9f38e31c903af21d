"""Result tables: per-trial rows, time series, percentile tables.

Percentiles use numpy's ``inverted_cdf`` method, which always returns the value of an
actual trial. Diverged trials are handled twice: in the ``all`` population their
errors count as ``+inf`` (so a high percentile shows that some trials were lost), in
the ``converged`` population they are left out and counted in ``diverged``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..core import errorstate as es
from ..mc.trial import ERROR_NAMES, ChunkResult

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

    Each row is reduced on its own as a contiguous 1-D array, so the result of a trial
    does not depend on how many trials share the array (numpy sums contiguous and
    strided axes in different orders, which changes the last bits).
    """
    flat = np.ascontiguousarray(a, dtype=float).reshape(-1, a.shape[-1])
    out = np.full(flat.shape[0], np.nan)
    for i, row in enumerate(flat):
        v = row[~np.isnan(row)]
        if v.size:
            out[i] = v.mean()
    return out.reshape(a.shape[:-1])


def trials_frame(chunk: ChunkResult, t: np.ndarray, window_start: float, seed: int) -> pd.DataFrame:
    """One row per trial x filter (deterministic columns only; timing is separate)."""
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
        d = {"trial": chunk.trials.astype(np.int64), "filter": [r.label] * B, "seed": np.full(B, seed, np.int64)}
        for j, name in enumerate(ERROR_NAMES):
            d[name] = means[:, j]
        for j, name in enumerate(ERROR_NAMES):
            d[f"final_{name}"] = final[:, j]
        d["diverged"] = div
        d["diverged_step"] = r.diverged_step.astype(np.int64)
        d["diverged_reason"] = r.diverged_reason
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
            d[f"final_sigma_ratio_{name}"] = r.k_sigma_ratio[:, j] if r.k_sigma_ratio is not None else np.nan
        for name in NEES_PARTS:
            d[f"{name}_mean"] = row_nanmean(r.nees_parts[name][:, w]) if name in r.nees_parts else np.full(B, np.nan)
        frames.append(pd.DataFrame(d))
    return pd.concat(frames, ignore_index=True)


def _fault_columns(chunk: ChunkResult, r) -> dict[str, np.ndarray]:
    """Per trial: features rejected by the filter's gate, and the tracker's dropouts and outliers (steps >= 1)."""
    B = len(chunk.trials)
    gated = np.zeros(B, np.int64) if r.gated is None else r.gated[:, 1:].sum(axis=1).astype(np.int64)
    f = chunk.faults
    drop = np.zeros(B, np.int64) if f is None else (~f.kept[:, 1:]).sum(axis=(1, 2)).astype(np.int64)
    out = np.zeros(B, np.int64) if f is None else f.outlier[:, 1:].sum(axis=(1, 2)).astype(np.int64)
    return {"gated_features": gated, "dropped_features": drop, "outlier_features": out}


def timing_frame(chunk: ChunkResult, chunk_id: int) -> pd.DataFrame:
    rows = []
    for r in chunk.runs:
        rows.append(pd.DataFrame({"trial": chunk.trials.astype(np.int64), "filter": r.label,
                                  "runtime_s": r.runtime_s, "chunk": chunk_id}))  # fmt: skip
    return pd.concat(rows, ignore_index=True)


def timeseries_frame(chunk: ChunkResult, t: np.ndarray, keep: np.ndarray | None = None) -> pd.DataFrame:
    """Per trial, filter and step: the six errors, NEES, NIS, IEKF iterations."""
    frames = []
    sel = np.ones(len(chunk.trials), bool) if keep is None else keep
    B = int(sel.sum())
    K1 = t.size
    if B == 0:
        return pd.DataFrame({c: [] for c in TS_COLUMNS})
    for r in chunk.runs:
        d = {
            "trial": np.repeat(chunk.trials[sel].astype(np.int64), K1),
            "filter": [r.label] * (B * K1),
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
        frames.append(pd.DataFrame(d))
    return pd.concat(frames, ignore_index=True)


def pct_value(p: float, percentiles: list[float]) -> int | float:
    """Percentiles are integers (50, 70, ...) unless the scenario asks for a fractional one (99.9)."""
    return int(p) if all(float(q).is_integer() for q in percentiles) else float(p)


def percentile_table(trials: pd.DataFrame, percentiles: list[float]) -> pd.DataFrame:
    """Percentiles of the per-trial window means, per filter and population."""
    rows = []
    for label, g in trials.groupby("filter", sort=False):
        div = g["diverged"].to_numpy()
        n, nd = len(g), int(div.sum())
        for pop in ("all", "converged"):
            vals = {}
            for name in ERROR_NAMES:
                v = g[name].to_numpy(dtype=float)
                if pop == "all":
                    v = np.where(div | ~np.isfinite(v), np.inf, v)
                else:
                    v = v[~div & np.isfinite(v)]
                vals[name] = v
            for p in percentiles:
                row = {"filter": label, "population": pop, "percentile": pct_value(p, percentiles)}
                for name in ERROR_NAMES:
                    v = vals[name]
                    row[name] = float(np.percentile(v, p, method="inverted_cdf")) if v.size else np.nan
                row["trials"] = n if pop == "all" else n - nd
                row["diverged"] = nd
                rows.append(row)
    cols = ["filter", "population", "percentile", *ERROR_NAMES, "trials", "diverged"]
    return pd.DataFrame(rows, columns=cols)


def _fmt(v: float) -> str:
    if not np.isfinite(v):
        return "inf" if v > 0 else "nan"
    return f"{v:.3g}"


def format_table(pt: pd.DataFrame, label: str, population: str = "converged", markdown: bool = False) -> str:
    """The thesis's layout: rows 50/70/90/100, columns rho, rho_dot, omega, theta, k1, k2."""
    g = pt[(pt["filter"] == label) & (pt["population"] == population)]
    head = ["pct"] + [ERROR_LABELS[n] for n in ERROR_NAMES]
    body = [[f"{p:g}"] + [_fmt(r[n]) for n in ERROR_NAMES] for p, r in zip(g["percentile"], g.to_dict("records"))]
    if markdown:
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(b) + " |" for b in body]
        return "\n".join(lines)
    widths = [max(len(x[i]) for x in [head] + body) for i in range(len(head))]
    fmt = lambda row: "  ".join(c.rjust(w) for c, w in zip(row, widths))  # noqa: E731
    return "\n".join([fmt(head), *map(fmt, body)])


UNOBSERVABLE_RATIO = 0.5  # final / initial sigma of a parameter above which the data did not reveal it


def not_observable(trials: pd.DataFrame, label: str) -> dict[str, float]:
    """Parameters (k1, k2) the converged trials of ``label`` carry at more than half their initial sigma.

    Maps each to its median final / initial standard deviation: the data did not reveal
    it, and (the trial being converged, so its error is within ``sigma_ratio`` of its own
    sigma) the filter says so honestly; it is not a failure.
    """
    g = trials[(trials["filter"] == label) & ~trials["diverged"].astype(bool)]
    out = {}
    for name in ("k1", "k2"):
        col = f"final_sigma_ratio_{name}"
        if col in g and len(g):
            m = float(np.nanmedian(g[col]))
            if m > UNOBSERVABLE_RATIO:
                out[name] = m
    return out


def population_note(trials: pd.DataFrame, label: str) -> str:
    """Which trials the two populations hold: the ids left out of ``converged``, by reason."""
    g = trials[(trials["filter"] == label) & trials["diverged"].astype(bool)]
    if g.empty:
        return "Both populations hold every trial.\n"
    lines = ["`converged` leaves out these trials (`all` holds them as +inf):\n"]
    for reason, h in g.groupby(g["diverged_reason"].str.split(":").str[0], sort=True):
        ids = sorted(int(t) for t in h["trial"])
        shown = ", ".join(map(str, ids[:30])) + (f", ... ({len(ids) - 30} more)" if len(ids) > 30 else "")
        lines.append(f"- {reason} ({len(ids)}): {shown}")
    return "\n".join(lines) + "\n"


def percentiles_markdown(pt: pd.DataFrame, trials: pd.DataFrame | None = None) -> str:
    out = []
    for label in dict.fromkeys(pt["filter"]):
        g = pt[pt["filter"] == label].iloc[0]
        n, nd = int(g["trials"]), int(g["diverged"])
        out.append(f"## {label}: {n - nd} of {n} trials converged ({nd} diverged)\n")
        if trials is not None:
            out.append(population_note(trials, label))
            for name, m in not_observable(trials, label).items():
                out.append(f"{name}: not observable in this run (median final sigma = {m:.2f} x the initial one; "
                           "carried with its covariance, not a failure).\n")
        out.append("Converged trials only:\n\n" + format_table(pt, label, "converged", markdown=True) + "\n")
        out.append("All trials (a diverged trial counts as +inf):\n\n" + format_table(pt, label, "all", markdown=True) + "\n")
    return "\n".join(out)
