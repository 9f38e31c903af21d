"""The report of a sweep (``spmc sweep``, ``spmc report DIR``): metrics against the swept values.

Writes ``DIR/sweep.csv`` (per point and filter: swept values, trials, divergence rate,
10/50/90th percentiles of each per-trial mean error over the converged trials),
``DIR/figures/sweep-<filter>.png|svg`` (median lines with 10-90 % bands, and the
divergence rate, against the first swept key; one line per value of the others) and
``DIR/report.html``; each point also gets its own run report and the folder an
``index.html``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from ..rundir import store
from ..rundir.tables import ERROR_LABELS, ERROR_NAMES
from ..studies import sweep as sw
from . import figures as figs
from .html import esc, figure_html, fmt_num, html_table, page
from .report import build_index, build_run_report


def _numeric(values: list) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def sweep_figure(summary: pd.DataFrame, spec: dict, label: str, x_axis: int = 0) -> Figure:
    """The metrics of one filter against swept key ``x_axis``; one line per value of the other keys (grid)."""
    axes_spec = spec["axes"]
    x_path = axes_spec[x_axis]["path"]
    others = [a["path"] for i, a in enumerate(axes_spec) if i != x_axis] if not spec.get("zip") else []
    g = summary[summary["filter"] == label]
    fig = Figure(figsize=(14, 6.8), layout="constrained")
    axs = fig.subplots(2, 4).ravel()
    fig.suptitle(f"{label}: per-trial mean errors (median, 10-90 % band of converged trials) against {x_path}")
    groups = list(g.groupby(others, sort=False)) if others else [((), g)]
    xs_all = list(dict.fromkeys(g[x_path].tolist()))
    numeric = _numeric(xs_all)
    for key, sub in groups:
        x = sub[x_path].to_numpy(float) if numeric else np.array([xs_all.index(v) for v in sub[x_path]], float)
        order = np.argsort(x, kind="stable")
        key = key if isinstance(key, tuple) else (key,)
        lab = ", ".join(f"{p.split('.')[-1]}={v}" for p, v in zip(others, key)) or None
        for ax, name in zip(axs, ERROR_NAMES):
            lo, med, hi = (sub[f"{name}_p{q}"].to_numpy(float)[order] for q in ("10", "50", "90"))
            line = ax.plot(x[order], med, marker="o", label=lab)[0]
            ax.fill_between(x[order], lo, hi, color=line.get_color(), alpha=0.2)
        axs[6].plot(x[order], 100 * sub["divergence_rate"].to_numpy(float)[order], marker="o", label=lab)
    for ax, name in zip(axs, ERROR_NAMES):
        ax.set_ylabel(ERROR_LABELS[name])
        figs.log_y(ax, *(np.asarray(line.get_ydata(), float) for line in ax.lines))
    axs[6].set_ylabel("diverged [%]")
    for ax in axs[:7]:
        ax.set_xlabel(x_path, fontsize=8)
        if not numeric:
            ax.set_xticks(range(len(xs_all)), [str(v) for v in xs_all], fontsize=7)
    if others:
        axs[6].legend(fontsize=7)
    axs[7].set_visible(False)
    return fig


def build_sweep_report(out: Path, jobs: int = 1) -> Path:
    """Write ``sweep.csv``, the sweep figures, every point's report, ``index.html`` and ``report.html`` (``jobs``:
    processes drawing the figures of each point, ``build_run_report``'s, and of the sweep)."""

    out = Path(out)
    spec = sw.load_sweep(out)
    missing = [p["name"] for p in spec["points"] if not (out / p["name"] / "trials.parquet").is_file()]
    if missing:
        raise sw.SweepError(f"{out}: unfinished points {', '.join(missing)}; rerun the sweep command to finish them")
    summary = sw.summary(out)
    store.atomic_write_text(out / "sweep.csv", summary.to_csv(index=False, float_format="%.6g"))
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    runs = [out / p["name"] for p in spec["points"]]
    for r in runs:
        build_run_report(r, jobs=jobs)
    build_index(out, runs)
    body = [f"<h1>Sweep of {esc(spec['scenario'])}</h1>",
            "<p>" + ("Zipped" if spec.get("zip") else "Grid") + " over "
            + ", ".join(f"<code>{esc(a['path'])}</code> = {esc(a['values'])}" for a in spec["axes"])
            + f"; {len(spec['points'])} points, each an ordinary run directory (same root seed: paired). "
            "Per point and filter: trials, divergence rate and the median [10th, 90th percentile] of each "
            "per-trial mean error over the converged trials. Tables: <code>sweep.csv</code>, "
            "<code>percentiles.csv</code> (for <code>spmc compare</code>); per-run reports: "
            "<a href=\"index.html\">index.html</a>.</p>"]  # fmt: skip
    paths = [a["path"] for a in spec["axes"]]
    heads = ["point", *paths, "filter", "trials", "diverged %"] + [ERROR_LABELS[n] for n in ERROR_NAMES]
    rows = []
    for r in summary.to_dict("records"):
        cells = [f"<a href=\"{esc(r['point'])}/report.html\">{esc(r['point'])}</a>", *[esc(r[p]) for p in paths],
                 esc(r["filter"]), str(r["trials"]), f"{100 * r['divergence_rate']:.1f}"]  # fmt: skip
        cells += [f"{fmt_num(r[f'{n}_p50'])} [{fmt_num(r[f'{n}_p10'])}, {fmt_num(r[f'{n}_p90'])}]" for n in ERROR_NAMES]
        rows.append(cells)
    body.append(html_table(heads, rows, left=len(paths) + 2))
    n_axes = 1 if spec.get("zip") else len(spec["axes"])
    todo = [(f"sweep-{figs.safe_name(label)}-{figs.safe_name(spec['axes'][k]['path'])}",
             f"{label} against {spec['axes'][k]['path']}",
             "Lines: medians; bands: 10-90 % of the converged trials; bottom right: share of diverged trials.",
             sweep_figure, (summary, spec, label, k))
            for label in dict.fromkeys(summary["filter"]) for k in range(n_axes)]  # fmt: skip
    body += [figure_html(f, out) for f in figs.drawn_files(todo, fig_dir, jobs, None)]
    path = out / "report.html"
    store.atomic_write_text(path, page(f"Sweep: {spec['scenario']}", body))
    return path
