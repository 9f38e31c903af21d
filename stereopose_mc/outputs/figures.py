"""Statistics figures of a run directory (thesis figures 6.1-6.14 and 6.37, table 6.7).

Every figure is drawn from the run's Parquet tables alone and saved twice, as PNG
(150 dpi) and SVG, into ``DIR/figures/``. Matplotlib is used through its object API
(``Figure`` + the Agg canvas), so importing this module never changes the global
backend. SVG output is made reproducible (fixed hash salt, no date).

Figures (``<f>`` is a filter label, made safe for file names):

- ``hist-<f>``: histograms of the six per-trial window-mean errors of converged trials;
- ``diff-ekf-iekf``: paired histograms of ``e_EKF - e_IEKF`` per error, over the trials
  where both filters converged (only when the run has an EKF and an IEKF);
- ``time-<f>``: error vs time over the trials of ``timeseries.parquet``: the median and the
  central 70 % (15th-85th percentile) and 90 % (5th-95th) bands, log y;
- ``nees-<f>`` / ``nis-<f>``: the median and 5th-95th percentile band over trials of NEES / NIS vs
  time (they set the axis), and the mean over trials with the two-sided
  95 % band of that mean for a consistent filter,
  ``[chi2.ppf(0.025, M d), chi2.ppf(0.975, M d)] / M`` with ``d = n - 1`` (``M`` trials alive at the step,
  ``n`` = state dimension for NEES, the step's measurement dimension for NIS);
- ``runtime``: histogram of the per-trial compute time (``timing.parquet``).

Tables written beside them: ``percentiles-<f>.csv|.md`` (the thesis layout) and
``compute_time.csv|.md`` (max / mean / min seconds per trial).
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import pandas as pd
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from ..rundir import store
from ..rundir.percentiles import percentile_table, percentiles_markdown
from ..rundir.tables import AXES, AXIS_UNITS, ERROR_LABELS, ERROR_NAMES
from ..studies.figure_files import save_figure

PANEL_SHAPE = (2, 3)
CENTRAL_BANDS = ((70.0, "#9ecae1"), (90.0, "#deebf7"))  # (coverage %, colour), drawn widest first


@dataclass(frozen=True)
class FigureFile:
    """One saved figure: a key, a title and caption for the report, and its two files."""

    key: str
    title: str
    caption: str
    png: Path
    svg: Path


@dataclass
class FigureSet:
    """What :func:`plan_figures` wrote and will draw (``drawn_files``), and why anything was skipped."""

    figures: list[FigureFile] = field(default_factory=list)
    tables: list[Path] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def safe_name(label: str) -> str:
    """A filter label made safe for a file name."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", str(label)) or "_"


def _panels(title: str) -> tuple[Figure, np.ndarray]:
    fig = Figure(figsize=(12, 6.8), layout="constrained")
    axes = fig.subplots(*PANEL_SHAPE).ravel()
    fig.suptitle(title)
    return fig, axes


def _bins(v: np.ndarray) -> int:
    """Histogram bin count: ``ceil(sqrt(n))`` clipped to [5, 40]."""
    return int(np.clip(np.ceil(np.sqrt(max(v.size, 1))), 5, 40))


# --------------------------------------------------------------------------- histograms

CLIP_IQR = 5.0  # histogram axes end at the quartiles -/+ 5 IQR (beyond Tukey's far-out fences)


def robust_range(v: np.ndarray) -> tuple[float, float]:
    """The x range that a few wild trials cannot stretch: [q25 - 5 IQR, q75 + 5 IQR] within [min, max]."""
    q25, q75 = np.percentile(v, [25, 75])
    iqr = q75 - q25
    if not iqr > 0:
        return float(v.min()), float(v.max())
    return max(float(v.min()), q25 - CLIP_IQR * iqr), min(float(v.max()), q75 + CLIP_IQR * iqr)


def clipped_hist(ax, v: np.ndarray, color: str) -> np.ndarray:
    """Histogram of ``v`` over its :func:`robust_range`; the trials beyond are counted in a note on the panel."""
    lo, hi = robust_range(v)
    inside = (v >= lo) & (v <= hi)
    ax.hist(v[inside], bins=_bins(v[inside]), color=color, edgecolor="white")
    out = v[~inside]
    if out.size:
        parts = []
        if np.any(out < lo):
            parts.append(f"{int(np.sum(out < lo))} below (min {out.min():.3g})")
        if np.any(out > hi):
            parts.append(f"{int(np.sum(out > hi))} above (max {out.max():.3g})")
        ax.text(0.98, 0.80, "clipped: " + ", ".join(parts) + " not shown", ha="right", va="top",
                transform=ax.transAxes, fontsize=7, color="#b22222",
                bbox={"facecolor": "white", "alpha": 0.85, "edgecolor": "#b22222", "lw": 0.5})  # fmt: skip
    return out


def error_histograms(trials: pd.DataFrame, label: str) -> Figure:
    """Histograms of the six per-trial window-mean errors of one filter (converged trials)."""
    g = trials[trials["filter"] == label]
    n, nd = len(g), int(g["diverged"].sum())
    fig, axes = _panels(f"{label}: per-trial mean errors, {n - nd} of {n} trials converged ({nd} diverged)")
    ok = ~g["diverged"].to_numpy(bool)
    for ax, name in zip(axes, ERROR_NAMES):
        v = g[name].to_numpy(float)[ok]
        v = v[np.isfinite(v)]
        if v.size:
            clipped_hist(ax, v, "#4c72b0")
            ax.axvline(np.median(v), color="k", ls="--", lw=1, label=f"median {np.median(v):.3g}")
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, "no converged trials", ha="center", va="center", transform=ax.transAxes)
        ax.set_xlabel(ERROR_LABELS[name])
        ax.set_ylabel("trials")
    return fig


def paired_differences(trials: pd.DataFrame, ekf: str, iekf: str) -> tuple[pd.DataFrame, int]:
    """Per trial ``e_EKF - e_IEKF`` of the six errors, over trials where both filters converged.

    Returns the differences (one row per kept trial, column ``trial`` + the six errors)
    and the number of trials the two filters have in common.
    """
    cols = ["trial", "diverged", *ERROR_NAMES]
    a = trials.loc[trials["filter"] == ekf, cols]
    b = trials.loc[trials["filter"] == iekf, cols]
    both = a.merge(b, on="trial", how="inner", suffixes=("_ekf", "_iekf")).sort_values("trial", kind="stable")
    ok = ~both["diverged_ekf"].to_numpy(bool) & ~both["diverged_iekf"].to_numpy(bool)
    for name in ERROR_NAMES:
        ok &= np.isfinite(both[f"{name}_ekf"].to_numpy(float)) & np.isfinite(both[f"{name}_iekf"].to_numpy(float))
    kept = both[ok]
    diff = pd.DataFrame({"trial": kept["trial"].to_numpy()})
    for name in ERROR_NAMES:
        diff[name] = kept[f"{name}_ekf"].to_numpy(float) - kept[f"{name}_iekf"].to_numpy(float)
    return diff, len(both)


def paired_difference_figure(diff: pd.DataFrame, n_common: int, ekf: str, iekf: str) -> Figure:
    """Histograms of ``e_EKF - e_IEKF`` (positive: the IEKF's error is smaller)."""
    n = len(diff)
    fig, axes = _panels(f"{ekf} - {iekf}: paired differences of per-trial mean errors, "
                        f"{n} of {n_common} trials where both converged")  # fmt: skip
    for ax, name in zip(axes, ERROR_NAMES):
        v = diff[name].to_numpy(float)
        if v.size:
            clipped_hist(ax, v, "#dd8452")
            ax.axvline(0.0, color="k", lw=1)
            ax.set_title(f"{iekf} lower in {int(np.sum(v > 0))} of {v.size}", fontsize=9)
        else:
            ax.text(0.5, 0.5, "no paired trials", ha="center", va="center", transform=ax.transAxes)
        ax.set_xlabel(f"{ERROR_LABELS[name]}: {ekf} - {iekf}")
        ax.set_ylabel("trials")
    return fig


# --------------------------------------------------------------------------- time series


def pivot(ts: pd.DataFrame, column: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(trials, t, A)`` with ``A[i, k]`` = ``column`` of trial ``trials[i]`` at step ``k`` (NaN if absent)."""
    trial_ids = np.unique(ts["trial"].to_numpy())
    steps = np.unique(ts["step"].to_numpy())
    ti = np.searchsorted(trial_ids, ts["trial"].to_numpy())
    si = np.searchsorted(steps, ts["step"].to_numpy())
    A = np.full((trial_ids.size, steps.size), np.nan)
    A[ti, si] = ts[column].to_numpy(float)
    t = np.full(steps.size, np.nan)
    t[si] = ts["t"].to_numpy(float)
    return trial_ids, t, A


def time_percentiles(A: np.ndarray, qs: list[float]) -> np.ndarray:
    """``(len(qs), K)`` percentiles over trials (axis 0) per step, ignoring NaN (diverged) trials."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanpercentile(A, qs, axis=0)


def live_trials(ax, t: np.ndarray, A: np.ndarray) -> None:
    """The count of live trials (a finite value) per step, as a grey step line on a right axis of ``ax``."""
    tw = ax.twinx()
    tw.step(t, np.isfinite(A).sum(axis=0), where="mid", color="grey", lw=0.8, alpha=0.8)
    tw.set_ylim(0, max(1, A.shape[0]) * 1.05)
    tw.set_ylabel("live trials", color="grey", fontsize=7)
    tw.tick_params(axis="y", labelsize=7, colors="grey")


def log_y(ax, *values: np.ndarray) -> None:
    """Log y when any plotted value is finite and positive; else a linear axis with a note (every
    trial non-finite, e.g. diverged at the first step: a log axis cannot be drawn)."""
    if any(np.any(np.isfinite(v) & (v > 0)) for v in map(np.asarray, values) if v.size):
        ax.set_yscale("log")
        return
    ax.text(0.5, 0.5, "no finite positive value to plot", ha="center", va="center", transform=ax.transAxes,
            fontsize=8, color="#b22222")  # fmt: skip


def error_vs_time_figure(ts: pd.DataFrame, label: str, window_start: float | None) -> Figure:
    """Median and central 70 % / 90 % bands over the live trials of each error vs time (log y), and their count."""
    g = ts[ts["filter"] == label]
    trial_ids = np.unique(g["trial"].to_numpy())
    _, _, E = pivot(g, ERROR_NAMES[0])
    live = np.isfinite(E).sum(axis=0)
    fig, axes = _panels(f"{label}: estimation error vs time over the live trials, {live.min() if live.size else 0}-"
                        f"{trial_ids.size} of {trial_ids.size} (grey, right axis; median, central 70 % and 90 % "
                        "bands)")  # fmt: skip
    for ax, name in zip(axes, ERROR_NAMES):
        _, t, A = pivot(g, name)
        live_trials(ax, t, A)
        for cover, colour in sorted(CENTRAL_BANDS, reverse=True):
            lo, hi = time_percentiles(A, [50 - cover / 2, 50 + cover / 2])
            ax.fill_between(t, lo, hi, color=colour, lw=0, label=f"{cover:g} % band")
        ax.plot(t, time_percentiles(A, [50])[0], color="#08519c", lw=1.5, label="median")
        if window_start is not None:
            ax.axvline(window_start, color="grey", ls=":", lw=1)
        log_y(ax, A)
        ax.set_xlabel("t [s]")
        ax.set_ylabel(ERROR_LABELS[name])
    axes[0].legend(fontsize=8)
    return fig


MAX_LINES = 100  # the per-axis figure draws the first this-many trials' lines (the envelope and fraction use all)


def axis_error_figure(ts: pd.DataFrame, label: str, window_start: float | None) -> Figure:
    """The Monte Carlo plot per axis: every trial's error (thin lines) and the median filter +-3 sigma envelope,
    with the fraction of (trial, step) pairs in the window whose error lies inside +-3 sigma."""
    g = ts[ts["filter"] == label]
    blocks = [AXES[i : i + 3] for i in range(0, 12, 3)] + [AXES[12:]]
    fig = Figure(figsize=(12, 13), layout="constrained")
    axes = fig.subplots(len(blocks), 3, squeeze=False)
    n_tr = g["trial"].nunique()
    for row, names in zip(axes, blocks):
        for ax, c in zip(row, names):
            _, t, E = pivot(g, f"err_{c}")
            _, _, S = pivot(g, f"sigma_{c}")
            # one collection of the trials' lines, not one artist per trial: ~30 % of the figure's time (100 trials)
            lines = np.stack(np.broadcast_arrays(t, E[:MAX_LINES]), axis=-1)  # (trials, steps, (t, err))
            ax.add_collection(LineCollection(lines, colors="#4a6fa5", linewidths=0.4, alpha=0.35))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                s3 = 3 * np.nanmedian(S, axis=0)
            ax.plot(t, s3, color="#d62728", lw=1.3, ls="--", label="median filter \u00b13\u03c3")
            ax.plot(t, -s3, color="#d62728", lw=1.3, ls="--")
            w = np.ones(t.shape, bool) if window_start is None else t >= window_start - 1e-9
            ok = np.isfinite(E[:, w]) & np.isfinite(S[:, w])
            inside = np.abs(E[:, w]) <= 3 * S[:, w]
            frac = float(inside[ok].mean()) if ok.any() else float("nan")
            ax.set_title(f"{c}: {100 * frac:.1f} % inside \u00b13\u03c3", fontsize=9)
            lim = np.nanmax(np.abs(s3[w])) if np.isfinite(s3[w]).any() else None
            if lim and lim > 0:
                ax.set_ylim(-3 * lim, 3 * lim)  # the envelope readable; a wild trial leaves the axis
            if window_start is not None:
                ax.axvline(window_start, color="grey", ls=":", lw=1)
            ax.set_ylabel(f"err [{AXIS_UNITS[c]}]", fontsize=8)
            ax.tick_params(labelsize=7)
        for ax in row[len(names) :]:
            ax.set_visible(False)
    axes[-1][0].set_xlabel("t [s]")
    axes[0][0].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{label}: error per axis, {min(n_tr, MAX_LINES)} of {n_tr} trials drawn; fraction inside \u00b13\u03c3 "
                 f"over t \u2265 {window_start if window_start is not None else 0:g} s, all {n_tr} trials")  # fmt: skip
    return fig


def mean_band(M: np.ndarray, dof: np.ndarray, level: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """Two-sided ``level`` band of the mean of ``M`` independent chi-square(``dof``) variables.

    ``M * mean ~ chi2(M * dof)``, so the band is ``chi2.ppf([a/2, 1 - a/2], M dof) / M``.
    NaN where ``M * dof == 0``.
    """
    M = np.asarray(M, float)
    dof = np.broadcast_to(np.asarray(dof, float), M.shape)
    a = 1.0 - level
    ok = (M > 0) & (dof > 0)
    lo = np.full(M.shape, np.nan)
    hi = np.full(M.shape, np.nan)
    from scipy.stats import chi2  # (here: a process that only draws figures, draw_all's, does without its 0.9 s)

    lo[ok] = chi2.ppf(a / 2, M[ok] * dof[ok]) / M[ok]
    hi[ok] = chi2.ppf(1 - a / 2, M[ok] * dof[ok]) / M[ok]
    return lo, hi


@dataclass(frozen=True)
class Consistency:
    """Mean over trials of NEES or NIS per step, the 95 % band and the trials alive ``M``."""

    t: np.ndarray
    mean: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    M: np.ndarray
    dof: np.ndarray
    quantiles: np.ndarray | None = None  # (3, steps): 5th, 50th, 95th percentile over the trials alive

    @property
    def inside(self) -> tuple[int, int]:
        """(steps whose mean is inside the band, steps with a band)."""
        ok = np.isfinite(self.lo) & np.isfinite(self.mean)
        return int(np.sum(ok & (self.mean >= self.lo) & (self.mean <= self.hi))), int(ok.sum())


def consistency(ts: pd.DataFrame, label: str, column: str, dof: int | None) -> Consistency:
    """Mean of ``column`` over the live trials per step and its 95 % band.

    ``dof`` is the state dimension for NEES; ``None`` is the NIS **per measurement dimension**: each trial's
    ``nis / nis_dof`` (its dimension varies between trials and steps under occlusion, dropouts and gating), the
    mean being ``sum(nis) / sum(nis_dof)`` over the live trials, whose band for a consistent filter is
    ``chi2.ppf([0.025, 0.975], D) / D`` with ``D = sum(nis_dof)`` (expected 1).
    """
    g = ts[ts["filter"] == label]
    _, t, A = pivot(g, column)
    if dof is None:
        _, _, D = pivot(g, "nis_dof")
        A = np.where(D > 0, A, np.nan)
    finite = np.isfinite(A)
    M = finite.sum(axis=0)
    if dof is None:
        tot = np.where(finite, D, 0.0).sum(axis=0)  # D = sum of the live trials' dimensions
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(tot > 0, np.where(finite, A, 0.0).sum(axis=0) / tot, np.nan)
            A = A / np.where(D > 0, D, np.nan)
        lo, hi = mean_band(np.ones_like(tot), tot)
        lo, hi = lo / np.where(tot > 0, tot, np.nan), hi / np.where(tot > 0, tot, np.nan)
        d = np.where(tot > 0, 1.0, np.nan)
    else:
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(M > 0, np.where(finite, A, 0.0).sum(axis=0) / np.maximum(M, 1), np.nan)
        d = np.full(t.shape, float(dof))
        lo, hi = mean_band(M, d)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        q = np.nanpercentile(A, [5, 50, 95], axis=0) if A.size else None
    return Consistency(t, mean, lo, hi, M, d, q)


def consistency_figure(c: Consistency, label: str, what: str, dof_text: str) -> Figure:
    """Mean NEES / NIS vs time with its 95 % chi-square band (log y)."""
    inside, steps = c.inside
    fig = Figure(figsize=(9, 4.5), layout="constrained")
    ax = fig.subplots()
    ok = np.isfinite(c.lo)
    ax.fill_between(c.t[ok], c.lo[ok], c.hi[ok], color="#c7e9c0", lw=0, label="95 % band for a consistent filter")
    ax.plot(c.t, c.mean, color="#238b45", lw=1.0, label=f"mean {what} over trials")
    if c.quantiles is not None:
        q05, q50, q95 = c.quantiles
        ax.fill_between(c.t, q05, q95, color="#6baed6", alpha=0.25, lw=0, label="5th-95th percentile over trials")
        ax.plot(c.t, q50, color="#08519c", lw=1.8, label=f"median {what} over trials")
        # the scale follows the median and the bands, not a mean that one diverging trial can dominate
        v = np.concatenate([q05[np.isfinite(q05)], q95[np.isfinite(q95)], c.lo[ok], c.hi[ok], c.dof[ok]])
        v = v[v > 0]
        if v.size:
            ax.set_ylim(0.5 * np.min(v), 2.0 * np.max(v))
    ax.plot(c.t[ok], c.dof[ok], color="k", ls=":", lw=1, label=f"expected ({dof_text})")
    log_y(ax, c.mean, c.lo[ok], c.hi[ok], c.dof[ok], *(() if c.quantiles is None else c.quantiles))
    _clip_y(ax, c)
    ax.set_xlabel("t [s]")
    ax.set_ylabel(what)
    m = int(np.max(c.M)) if c.M.size else 0
    tw = ax.twinx()
    tw.step(c.t, c.M, where="mid", color="grey", lw=0.8, alpha=0.8)
    tw.set_ylim(0, max(1, m) * 1.05)
    tw.set_ylabel("live trials", color="grey", fontsize=8)
    tw.tick_params(axis="y", labelsize=7, colors="grey")
    low = int(np.min(c.M[c.M > 0])) if (c.M > 0).any() else 0
    ax.set_title(f"{label}: {what} over the live trials ({low}-{m}, grey); mean inside its band at {inside} of {steps} "
                 "steps", fontsize=10)  # fmt: skip
    ax.legend(fontsize=8)
    return fig


def _clip_y(ax, c: Consistency, decades: float = 2.0) -> None:
    """Keep the band readable: the y axis ends ``decades`` above / below the band; a mean beyond is noted."""
    band = np.concatenate([c.lo[np.isfinite(c.lo)], c.hi[np.isfinite(c.hi)]])
    m = c.mean[np.isfinite(c.mean) & (c.mean > 0)]
    if not band.size or not m.size:
        return
    top, bottom = band.max() * 10**decades, band.min() / 10**decades
    if m.max() > top or m.min() < bottom:
        ax.set_ylim(max(bottom, m.min() / 2), min(top, m.max() * 2))
        n_out = int(np.sum((m > top) | (m < bottom)))
        ax.text(0.99, 0.02, f"clipped: the mean is beyond the axis at {n_out} steps (max {m.max():.3g})",
                ha="right", va="bottom", transform=ax.transAxes, fontsize=7, color="#b22222")  # fmt: skip


# --------------------------------------------------------------------------- compute time


def compute_time_table(timing: pd.DataFrame) -> pd.DataFrame:
    """Per filter: trials, max, mean and min compute time per trial [s] (thesis table 6.7)."""
    rows = []
    for label, g in timing.groupby("filter", sort=False):
        v = g["runtime_s"].to_numpy(float)
        rows.append({"filter": label, "trials": int(v.size), "max_s": float(np.max(v)),
                     "mean_s": float(np.mean(v)), "min_s": float(np.min(v))})  # fmt: skip
    return pd.DataFrame(rows, columns=["filter", "trials", "max_s", "mean_s", "min_s"])


def compute_time_figure(timing: pd.DataFrame) -> Figure:
    """Histogram of the per-trial compute time, one colour per filter."""
    fig = Figure(figsize=(9, 4.5), layout="constrained")
    ax = fig.subplots()
    v_all = timing["runtime_s"].to_numpy(float)
    edges = np.histogram_bin_edges(v_all, bins=_bins(v_all)) if v_all.size else 10
    for label, g in timing.groupby("filter", sort=False):
        ax.hist(g["runtime_s"].to_numpy(float), bins=edges, alpha=0.6, label=str(label), edgecolor="white")
    ax.set_xlabel("compute time per trial [s]")
    ax.set_ylabel("trials")
    ax.set_title("Compute time per trial (a filter's wall time on a chunk, shared equally by its trials)")
    ax.legend(fontsize=8)
    return fig


# --------------------------------------------------------------------------- driver


def _markdown_table(df: pd.DataFrame) -> str:
    head = "| " + " | ".join(map(str, df.columns)) + " |"
    sep = "|" + "---|" * len(df.columns)
    body = ["| " + " | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row) + " |"
            for row in df.itertuples(index=False)]  # fmt: skip
    return "\n".join([head, sep, *body]) + "\n"


def ekf_iekf_pair(filters: list[str], types: dict[str, str]) -> tuple[str, str] | None:
    """The (EKF, IEKF) labels to pair: labels ``ekf`` and ``iekf`` if both exist, else the
    only filter of each type; ``None`` when there is no such pair."""
    if "ekf" in filters and "iekf" in filters:
        return "ekf", "iekf"
    from ..filters.registry import thesis_role  # (here: the drawing processes do without the registry's imports)

    e = [f for f in filters if thesis_role(types.get(f)) == "ekf"]
    i = [f for f in filters if thesis_role(types.get(f)) == "iekf"]
    return (e[0], i[0]) if len(e) == 1 and len(i) == 1 else None


def drawn_files(todo: list[tuple], out_dir: Path, jobs: int,
                progress: Callable[[str], None] | None) -> list[FigureFile]:  # fmt: skip
    """The ``FigureFile`` of each ``(key, title, caption, builder, args)`` of ``todo``, drawn by ``draw_all``."""
    return [FigureFile(key, title, caption, png, svg)
            for (key, title, caption, _, _), (png, svg) in zip(todo, draw_all(todo, out_dir, jobs, progress))]


def plan_figures(
    out_dir: Path,
    trials: pd.DataFrame,
    timeseries: pd.DataFrame | None,
    timing: pd.DataFrame | None,
    *,
    filters: list[str],
    filter_types: dict[str, str],
    state_dim: int | None,
    window_start: float | None,
    percentiles: list[float],
) -> tuple[FigureSet, list[tuple]]:
    """The tables (written into ``out_dir`` now) and the figures to draw, ``(key, title, caption, builder, args)``
    each (``draw_all``), that the inputs allow; the set notes what is skipped."""
    out_dir.mkdir(parents=True, exist_ok=True)
    fs = FigureSet()
    todo: list[tuple[str, str, str, Callable[..., Figure], tuple]] = []  # (key, title, caption, builder, its args)

    def add(builder: Callable[..., Figure], args: tuple, key: str, title: str, caption: str) -> None:
        todo.append((key, title, caption, builder, args))

    pt = percentile_table(trials, percentiles)
    for label in filters:
        s = safe_name(label)
        sub = pt[pt["filter"] == label]
        store.atomic_write_text(out_dir / f"percentiles-{s}.csv", sub.to_csv(index=False, float_format="%.10g"))
        store.atomic_write_text(out_dir / f"percentiles-{s}.md", f"# {label}\n\n" + percentiles_markdown(sub))
        fs.tables += [out_dir / f"percentiles-{s}.csv", out_dir / f"percentiles-{s}.md"]
    for label in filters:
        add(error_histograms, (trials, label), f"hist-{safe_name(label)}", f"{label}: histograms of per-trial errors",
            "Per-trial mean error over the error window, trials not lost (thesis figures 6.8-6.13).")  # fmt: skip

    pair = ekf_iekf_pair(filters, filter_types)
    if pair is None:
        fs.notes.append("paired EKF - IEKF histograms skipped: the run does not have both an EKF and an IEKF filter")
    else:
        diff, n_common = paired_differences(trials, *pair)
        add(paired_difference_figure, (diff, n_common, *pair), "diff-ekf-iekf",
            f"{pair[0]} - {pair[1]}: paired differences",
            f"Per trial, {pair[0]} error minus {pair[1]} error, over the {len(diff)} of {n_common} trials where both "
            "converged; positive means the IEKF did better (thesis figures 6.7, 6.14).")  # fmt: skip

    if timeseries is None or timeseries.empty:
        fs.notes.append("error/NEES/NIS vs time figures skipped: the run has no timeseries.parquet (--timeseries none)")
    else:
        for label in filters:
            if not (timeseries["filter"] == label).any():
                fs.notes.append(f"{label}: no rows in timeseries.parquet; its time figures are skipped")
                continue
            s = safe_name(label)
            g = timeseries[timeseries["filter"] == label]  # (the rows a drawing process is sent)
            n_ts = g["trial"].nunique()
            add(error_vs_time_figure, (_columns(g, ERROR_NAMES), label, window_start), f"time-{s}",
                f"{label}: error vs time",
                f"Median over the live trials (of the {n_ts} of timeseries.parquet; a lost trial leaves at the step it "
                "was lost, grey line and right axis: their count) and central bands holding 70 % (15th-85th "
                "percentile) and 90 % (5th-95th) of them; dotted line: start of the error window "
                "(thesis figures 6.1-6.6).")  # fmt: skip
            if f"err_{AXES[0]}" in timeseries:
                add(axis_error_figure, (_columns(g, [f"{w}_{c}" for c in AXES for w in ("err", "sigma")]), label,
                                        window_start), f"axes-{s}", f"{label}: error per axis vs 3 sigma",
                    "Every trial's error per axis (thin lines; the attitude chart's components, theta the attitude "
                    "error vector) and the median over trials of the filter's own \u00b13\u03c3 (dashed); each title "
                    "gives the fraction of the error-window steps of all trials inside \u00b13\u03c3 (about 99.7 % "
                    "for a consistent, Gaussian filter).")  # fmt: skip
            if state_dim:
                # the unit-norm quaternion takes one direction out of the state error: n - 1 dof
                dof = state_dim - 1
                c = consistency(g, label, "nees", dof)
                add(consistency_figure, (c, label, "NEES", f"{dof} dof (n = {state_dim}, unit quaternion)"),
                    f"nees-{s}", f"{label}: NEES vs time",
                    f"Median and 5th-95th percentile of the NEES over the trials alive at each step (the axis follows "
                    f"them), and their mean with its band chi2.ppf([0.025, 0.975], M*{dof})/M "
                    f"with {dof} = n - 1 degrees of freedom (the quaternion's norm is not an error direction).")
            else:
                fs.notes.append(f"{label}: NEES figure skipped: manifest.json has no state_dim")
            c = consistency(g, label, "nis", None)
            add(consistency_figure, (c, label, "NIS / dof", "1 per dimension"), f"nis-{s}", f"{label}: NIS vs time",
                "NIS per measurement dimension (nis / nis_dof; the dimension varies with visibility, dropouts and "
                "gating): median and 5th-95th percentile over the trials alive at each step, and sum(nis) / "
                "sum(nis_dof) over them with its band chi2.ppf([0.025, 0.975], D)/D, D = sum(nis_dof); grey: the "
                "live trials.")  # fmt: skip

    if timing is None or timing.empty:
        fs.notes.append("compute-time histogram skipped: the run has no timing.parquet")
    else:
        ct = compute_time_table(timing)
        store.atomic_write_text(out_dir / "compute_time.csv", ct.to_csv(index=False, float_format="%.6g"))
        store.atomic_write_text(out_dir / "compute_time.md", "# Compute time per trial [s]\n\n" + _markdown_table(ct))
        fs.tables += [out_dir / "compute_time.csv", out_dir / "compute_time.md"]
        add(compute_time_figure, (timing,), "runtime", "Compute time per trial",
            "Per-trial compute time from timing.parquet (thesis figure 6.37): a filter's wall time on a chunk "
            "of trials stepped together, divided by the chunk's trial count, so the spread is between chunks.")
    return fs, todo


def _columns(ts: pd.DataFrame, names: list[str]) -> pd.DataFrame:
    """The rows of ``ts`` with the columns a figure reads (``pivot``'s and ``names`` present)."""
    return ts[[c for c in ("filter", "trial", "step", "t", *names) if c in ts.columns]]


def _drawn(builder: Callable[..., Figure], args: tuple, out_dir: Path, key: str) -> tuple[Path, Path]:
    """``save_figure`` of ``builder(*args)`` as ``key``: one figure's whole work, in whichever process runs it."""
    return save_figure(builder(*args), out_dir, key)


def draw_all(todo: list[tuple], out_dir: Path, jobs: int,
             progress: Callable[[str], None] | None) -> Iterator[tuple[Path, Path]]:  # fmt: skip
    """``(png, svg)`` of each ``(key, title, caption, builder, args)`` of ``todo``, in its order.

    Matplotlib draws in Python, holding the GIL: threads would not help. With ``jobs > 1`` the figures go to up to
    ``jobs`` loky processes (an executor of this module's: later reports of the same command reuse them, their start,
    ~2-4 s here, is paid once; ``stop_drawing`` ends them), each drawing and saving whole figures from the rows it
    is sent; one job, or one figure, draws here. The files are the same either way (tests/outputs). ``progress(key)``
    as each figure is written, in ``todo``'s order.
    """
    if jobs <= 1 or len(todo) < 2:
        for key, _, _, builder, args in todo:
            if progress is not None:
                progress(key)
            yield _drawn(builder, args, out_dir, key)
        return
    global _POOL
    if _POOL is None:  # one executor of its own for every report of a command (not loky's global reusable one, which
        # joblib's loky backend, the engine's, takes over with its own attributes)
        import atexit

        from joblib.externals.loky import ProcessPoolExecutor

        _POOL = ProcessPoolExecutor(max_workers=jobs)
        atexit.register(stop_drawing)  # (an API user's process: shut down before the interpreter's teardown)
    pool = _POOL
    futures = [pool.submit(_drawn, builder, args, out_dir, key) for key, _, _, builder, args in todo]
    try:
        for (key, *_), f in zip(todo, futures):
            paths = f.result()
            if progress is not None:
                progress(key)
            yield paths
    finally:  # an error, or Ctrl-C: the figures not started are not drawn, those being drawn are waited for (the
        # caller then removes the staging directory they write into: none is left behind)
        from concurrent.futures import wait

        wait([f for f in futures if not f.cancel()])


_POOL = None  # the executor draw_all started (joblib.externals.loky's ProcessPoolExecutor), until stop_drawing


def stop_drawing() -> None:
    """Shut down the processes ``draw_all`` started (and the executor's thread, which would keep the interpreter
    from its fast exit: ``cli.main.exit_now``); nothing if it started none."""
    global _POOL
    pool, _POOL = _POOL, None
    if pool is not None:
        pool.shutdown(wait=True, kill_workers=True)  # (idle: nothing left to finish)
