"""The sensitivity section of a dispersed run's report: tables, CSV files, figures.

Written by ``spmc report`` whenever the run's scenario has ``dispersions``: ``sensitivity.csv``
(every filter x metric x parameter), ``sobol.csv`` (sobol campaigns), per filter a
heat map of the correlations and scatter plots of the top drivers, and the HTML
section (docs/sensitivity.md explains how to read them).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from ..config.schema import Scenario
from ..rundir.tables import ERROR_LABELS
from ..studies import sensitivity as sens
from . import figures as figs
from .html import esc, html_table
from ..rundir import store

TOP_SCATTER = 6


def _label(metric: str) -> str:
    return ERROR_LABELS.get(metric, metric)


def heatmap(table: pd.DataFrame, label: str, params: list[str]) -> Figure:
    """Correlation of every parameter (rows) with every metric (columns) for one filter."""
    g = table[table["filter"] == label]
    M = np.full((len(params), len(sens.METRICS)), np.nan)
    for r in g.itertuples():
        M[params.index(r.parameter), sens.METRICS.index(r.metric)] = r.value
    fig = Figure(figsize=(8, 0.28 * len(params) + 2.2), layout="constrained")
    ax = fig.subplots()
    im = ax.imshow(M, cmap="RdBu_r", vmin=-1, vmax=1, aspect="auto")
    ax.set_xticks(range(len(sens.METRICS)), [_label(m) for m in sens.METRICS], rotation=30, ha="right")
    ax.set_yticks(range(len(params)), params, fontsize=7)
    fig.colorbar(im, ax=ax, label="Spearman rho (errors) / rank-biserial r (diverged)")
    ax.set_title(f"{label}: what drives the error")
    return fig


def _top_pairs(table: pd.DataFrame, label: str, top: int = TOP_SCATTER) -> pd.DataFrame:
    """The filter's ``top`` (metric, parameter) rows of ``table`` with the largest |Spearman rho|, largest first."""
    g = table[(table["filter"] == label) & (table["statistic"] == "spearman")]
    return g.reindex(g["value"].abs().sort_values(ascending=False, kind="stable").index).head(top)


def _columns(trials: pd.DataFrame, label: str, top: pd.DataFrame) -> pd.DataFrame:
    """The filter's valid trials with the columns ``scatter_top`` reads (the rows a drawing process is sent)."""
    t = trials[trials["filter"] == label]
    t = t[~t["invalid"]] if "invalid" in t else t
    return t[list(dict.fromkeys(["diverged", *top["parameter"], *top["metric"]]))]


def scatter_top(t: pd.DataFrame, g: pd.DataFrame, label: str) -> Figure:
    """Scatter plots of the (metric, parameter) pairs ``g`` (``_top_pairs``) over the filter's trials ``t``."""
    fig, axes = figs._panels(f"{label}: top drivers (converged trials; diverged marked at the top edge)")
    for ax, r in zip(axes, g.itertuples()):
        ok = ~t["diverged"].to_numpy(bool)
        x, y = t[r.parameter].to_numpy(float), t[r.metric].to_numpy(float)
        ax.scatter(x[ok], y[ok], s=8, alpha=0.6)
        if (~ok).any():
            top_y = np.nanmax(y[ok]) if ok.any() else 1.0
            ax.scatter(x[~ok], np.full((~ok).sum(), top_y), marker="x", color="#d62728", s=14, label="diverged")
            ax.legend(fontsize=7, loc="upper right")
        if np.all(y[ok] > 0):
            ax.set_yscale("log")
        ax.set_xlabel(r.parameter, fontsize=8)
        ax.set_ylabel(_label(r.metric))
        ax.set_title(f"rho = {r.value:+.2f} [{r.ci_low:+.2f}, {r.ci_high:+.2f}]", fontsize=9)
    for ax in axes[len(g) :]:
        ax.set_visible(False)
    return fig


def _fmt(v: float, digits: int = 2) -> str:
    return "" if not np.isfinite(v) else f"{v:+.{digits}f}"


def section(run_dir: Path, trials: pd.DataFrame, config: dict, filters: list[str]) -> tuple[list[str], list[tuple]]:
    """HTML blocks and figures to draw of the sensitivity analysis (empty for a run without dispersions): the
    figures as ``(key, title, caption, builder, args)``, drawn with the report's own (``figures.drawn_files``)."""
    if not config.get("dispersions"):
        return [], []
    try:
        scn = Scenario.model_validate(config)
    except ValueError as exc:
        return [f"<h2>Sensitivity</h2><p>The stored scenario does not validate ({esc(str(exc).splitlines()[0])}).</p>"], []
    res = sens.analyze(trials, scn)
    body = ["<h2>Sensitivity: what drives the error</h2>"]
    if res is None:
        return body + ["<p>No dispersed scalar varies in this run.</p>"], []
    store.atomic_write_text(run_dir / "sensitivity.csv", res.table.to_csv(index=False, float_format="%.6g"))
    if res.table.empty:
        return body + [f"<p>Too few converged, valid trials for any correlation ({res.invalid} invalid draws).</p>"], []
    n_pairs = res.table.groupby("filter").size().max() if len(res.table) else 0
    body.append(
        "<p>For each filter, metric and dispersed scalar: Spearman's rank correlation of the scalar with the "
        "per-trial mean error (converged trials) with its 95 % interval, and for divergence the rank-biserial "
        "correlation between diverged and converged trials (positive: larger values diverge more). "
        f"<b>significant</b> = p below 0.05 / {n_pairs} (Bonferroni over the filter's pairs). "
        f"Sampling: <code>{esc(scn.dispersions.sampling)}</code>. "
        f"{res.invalid} invalid draw(s) left out. Full table: <code>sensitivity.csv</code>.</p>"
    )  # fmt: skip
    todo: list[tuple] = []
    params = sens.parameter_columns(trials, scn)
    for label in filters:
        d = sens.drivers(res.table, label)
        if d.empty:
            continue
        rows = [[esc(_label(r.metric)), str(r.rank), esc(r.parameter), _fmt(r.value), (f"[{_fmt(r.ci_low)}, "
                 f"{_fmt(r.ci_high)}]" if np.isfinite(r.ci_low) else ""), f"{r.p:.2g}", str(r.n),
                 "yes" if r.significant else ""] for r in d.itertuples()]  # fmt: skip
        body.append(html_table(["metric", "rank", "parameter", "rho / r", "95 % CI", "p", "n", "significant"], rows,
                               left=3, caption=f"{label}: the three strongest drivers of each metric"))  # fmt: skip
        todo.append((f"sensitivity-heatmap-{figs.safe_name(label)}",
                     f"{label}: correlation of every dispersed scalar with every metric",
                     "Spearman rho of the converged trials' mean errors; rank-biserial r for divergence.", heatmap,
                     (res.table, label, params)))  # fmt: skip
        top = _top_pairs(res.table, label)
        if not top.empty:
            todo.append((f"sensitivity-scatter-{figs.safe_name(label)}", f"{label}: scatter plots of the top drivers",
                         f"The {len(top)} (metric, scalar) pairs with the largest |rho|.", scatter_top,
                         (_columns(trials, label, top), top, label)))  # fmt: skip
    if res.sobol is not None:
        store.atomic_write_text(run_dir / "sobol.csv", res.sobol.to_csv(index=False, float_format="%.6g"))
        body.append("<h3>Sobol indices (SALib)</h3><p>First-order S1 and total ST indices of each input factor "
                    "(the unit-cube coordinates of the plan), with SALib's 95 % bootstrap half-widths; the factors "
                    "with the largest ST per metric. Full table: <code>sobol.csv</code>.</p>")  # fmt: skip
        for label in filters:
            g = res.sobol[res.sobol["filter"] == label]
            if g.empty:
                continue
            g = g.sort_values(["metric", "ST"], ascending=[True, False]).groupby("metric", sort=False).head(3)
            rows = [[esc(_label(r.metric)), esc(r.factor), f"{r.S1:.3f} ± {r.S1_conf:.3f}", f"{r.ST:.3f} ± {r.ST_conf:.3f}"]
                    for r in g.itertuples()]  # fmt: skip
            body.append(html_table(["metric", "factor", "S1", "ST"], rows, left=2, caption=f"{label}: Sobol indices"))
    if res.notes:
        body.append("<ul>" + "".join(f"<li>{esc(n)}</li>" for n in res.notes) + "</ul>")
    return body, todo
