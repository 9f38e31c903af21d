"""The report's section on tracker faults and gating (columns of trials.parquet).

Shown only when the run had faults or a gated filter: per filter, the features the
tracker dropped and the outliers it delivered (the same in every filter of a trial),
and the features the filter's gate rejected, as totals and per-trial medians.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .html import esc, html_table

if TYPE_CHECKING:
    from .report import RunData

COLUMNS = ("dropped_features", "outlier_features", "gated_features")


def fault_rows(data: RunData) -> list[list[str]]:
    """Per filter: total and median per trial of each fault column."""
    t = data.trials
    if not all(c in t for c in COLUMNS) or not t[list(COLUMNS)].to_numpy().any():
        return []
    rows = []
    for label in data.filters:
        g = t[t["filter"] == label]
        cells = [esc(label)]
        for c in COLUMNS:
            v = g[c].to_numpy(np.int64)
            cells += [str(int(v.sum())), f"{float(np.median(v)):g}" if v.size else "-"]
        rows.append(cells)
    return rows


def section(data: RunData) -> list[str]:
    """HTML of the section (empty without faults or gating)."""
    rows = fault_rows(data)
    if not rows:
        return []
    heads = ["filter", "dropped (total)", "dropped (median/trial)", "outliers (total)", "outliers (median/trial)",
             "gated out (total)", "gated out (median/trial)"]  # fmt: skip
    return ["<h2>Tracker faults and gating</h2>",
            "<p>Features the tracker dropped or mismatched (outliers), and features each filter's chi-square gate "
            "rejected before its update, over steps t &gt; 0 (per-step counts: column <code>gated</code> of "
            "timeseries.parquet).</p>",
            html_table(heads, rows)]  # fmt: skip
