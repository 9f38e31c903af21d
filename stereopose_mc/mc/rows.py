"""A chunk's results as rows of the run's tables (``trials``, ``timing``, ``timeseries``).

The column names and units are those of ``rundir/tables.py``; each builder returns
:data:`~stereopose_mc.rundir.tables.Columns`, filter-major.
"""

from __future__ import annotations

import math

import numpy as np

from ..core import errorstate as es
from ..rundir.tables import AXES, ERROR_NAMES, NEES_PARTS, Columns, concat_columns, strings
from .trial import ChunkResult


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


def trials_columns(chunk: ChunkResult, t: np.ndarray, window_start: float, seed: int) -> Columns:
    """One row per filter x trial, filter-major (deterministic columns only; timing is separate)."""
    w = window_mask(t, window_start)
    frames = []
    for r in chunk.runs:
        B = len(chunk.trials)
        div = r.lost_step >= 0
        means = row_nanmean(np.moveaxis(r.errors[:, w], 1, -1))
        it_mean = row_nanmean(np.where(r.iterations[:, 1:] > 0, r.iterations[:, 1:], np.nan))
        nees_mean = row_nanmean(r.nees[:, w])
        nis_mean = row_nanmean(r.nis[:, w])
        means[div] = np.nan
        final = r.errors[:, -1]
        d = {"trial": chunk.trials.astype(np.int64), "filter": strings(r.label, B), "seed": np.full(B, seed, np.int64)}
        for j, name in enumerate(ERROR_NAMES):
            d[name] = means[:, j]
        for j, name in enumerate(ERROR_NAMES):
            d[f"final_{name}"] = final[:, j]
        d["lost"] = div
        d["lost_step"] = r.lost_step.astype(np.int64)
        d["lost_reason"] = strings(r.lost_reason)
        d["inconsistent"] = r.inconsistent_step >= 0
        d["inconsistent_step"] = r.inconsistent_step.astype(np.int64)
        d["inconsistent_reason"] = strings(r.inconsistent_reason)
        d["diverged"], d["diverged_step"], d["diverged_reason"] = d["lost"], d["lost_step"], d["lost_reason"]  # aliases
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
        d["inside_3sigma"] = inside_3sigma(r, w)
        dofs = es.nees_dof(r.state_dim) if r.state_dim else {"nees": -1, "nees_gauge": -1}
        d["nees_dof"] = np.full(B, dofs["nees"], np.int64)  # so that any NEES can be normalised by a reader
        d["nees_gauge_dof"] = np.full(B, dofs["nees_gauge"], np.int64)
        for name in NEES_PARTS:  # the mean degrees of freedom over the window (feature slots: occupied ones only)
            if r.nees_dof_steps is not None and name in r.nees_dof_steps:
                d[f"dof_{name}"] = r.nees_dof_steps[name][:, w].mean(axis=1).astype(float)
            else:
                d[f"dof_{name}"] = np.full(B, float(dofs.get(name, np.nan)))
        if r.nees_dof_steps is not None:
            d["nees_dof"] = np.rint(r.nees_dof_steps["nees"][:, w].mean(axis=1)).astype(np.int64)
            d["nees_gauge_dof"] = np.rint(d["dof_nees_gauge"]).astype(np.int64)
        frames.append(d)
    return concat_columns(frames)


def inside_3sigma(r, w: np.ndarray) -> np.ndarray:
    """Per trial, the fraction of (step, axis) pairs of the window with ``|err_c| <= 3 sigma_c`` (NaN: none finite)."""
    B = r.lost_step.shape[0]
    if r.axis_err is None:
        return np.full(B, np.nan)
    e, s = r.axis_err[:, w], r.axis_sigma[:, w]
    ok = np.isfinite(e) & np.isfinite(s)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok.any(axis=(1, 2)), (ok & (np.abs(e) <= 3 * s)).sum(axis=(1, 2)) / ok.sum(axis=(1, 2)), np.nan)


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
    return concat_columns([{"trial": chunk.trials.astype(np.int64), "filter": strings(r.label, B),
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
            "filter": strings(r.label, B * K1),
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
        for pre, a in (("err", r.axis_err), ("sigma", r.axis_sigma)):
            for j, c in enumerate(AXES):
                d[f"{pre}_{c}"] = a[sel, :, j].reshape(-1) if a is not None else np.full(B * K1, np.nan)
        frames.append(d)
    return concat_columns(frames)
