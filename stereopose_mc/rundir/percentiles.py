"""The percentile table of a run: percentiles of the per-trial window means, and its text forms.

Percentiles use numpy's ``inverted_cdf`` method, which always returns the value of an
actual trial. Diverged trials are handled twice: in the ``all`` population their
errors count as ``+inf`` (so a high percentile shows that some trials were lost), in
the ``converged`` population they are left out and counted in ``diverged``.
:func:`percentile_columns` is what the run writes (``percentiles.csv|.md|.parquet``);
:func:`percentile_table` returns it as a DataFrame for the report and the studies.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from .tables import ERROR_LABELS, ERROR_NAMES, Columns, columns_of, strings, take_rows

if TYPE_CHECKING:
    import pandas as pd


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
    out: Columns = {"filter": strings(rows["filter"]), "population": strings(rows["population"]),
                    "percentile": np.asarray(rows["percentile"], np.int64 if integral else float)}  # fmt: skip
    out.update({name: np.asarray(rows[name], float) for name in ERROR_NAMES})
    out.update(trials=np.asarray(rows["trials"], np.int64), diverged=np.asarray(rows["diverged"], np.int64))
    return out


def percentile_table(trials: Any, percentiles: list[float]) -> pd.DataFrame:
    """:func:`percentile_columns` as a DataFrame (for the report, the studies and the docs)."""
    import pandas as pd

    return pd.DataFrame(percentile_columns(trials, percentiles))


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
