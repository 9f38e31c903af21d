"""The percentile table of a run: percentiles of the per-trial window means, and its text forms.

Percentiles use numpy's ``inverted_cdf`` method, which always returns the value of an
actual trial. Lost trials are handled twice: in the ``all`` population their errors
count as ``+inf`` (so a high percentile shows that some trials were lost), in the
``converged`` population (the trials not lost) they are left out and counted in
``lost``. Inconsistent trials (a truth-based flag) count like any other unless the
scenario asks to exclude them (``divergence.exclude_inconsistent``): then they are
handled as lost trials are. Rates come with their 95 % Wilson interval
(:func:`wilson_interval`).
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


def excluded(c: Columns, exclude_inconsistent: bool = False) -> np.ndarray:
    """Per row, left out of the statistics: lost, or (``exclude_inconsistent``) flagged inconsistent."""
    lost = np.asarray(c["lost"] if "lost" in c else c["diverged"]).astype(bool)
    if exclude_inconsistent and "inconsistent" in c:
        return lost | np.asarray(c["inconsistent"]).astype(bool)
    return lost


def percentile_columns(trials: Any, percentiles: list[float], exclude_inconsistent: bool = False) -> Columns:
    """Percentiles of the per-trial window means, per filter (in order of appearance) and population.

    ``converged``: the trials not lost (nor inconsistent with ``exclude_inconsistent``); ``all``: every trial,
    those left out of ``converged`` as ``+inf``. ``trials`` counts the population; ``lost`` and ``inconsistent``
    the filter's trials with each flag (``diverged``: ``lost``, an alias for one release).
    """
    c = columns_of(trials)
    filt = c["filter"]
    out_all = excluded(c, exclude_inconsistent)
    lost_all = excluded(c)
    incons_all = np.asarray(c["inconsistent"]).astype(bool) if "inconsistent" in c else np.zeros(filt.size, bool)
    counts = ("trials", "lost", "inconsistent", "diverged")
    rows: dict[str, list] = {k: [] for k in ("filter", "population", "percentile", *ERROR_NAMES, *counts)}
    for label in dict.fromkeys(filt.tolist()):
        g = filt == label
        div = out_all[g]
        n, nd = int(g.sum()), int(div.sum())
        nl, ni = int(lost_all[g].sum()), int(incons_all[g].sum())
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
                rows["lost"].append(nl)
                rows["inconsistent"].append(ni)
                rows["diverged"].append(nl)
    integral = all(float(q).is_integer() for q in percentiles)
    out: Columns = {"filter": strings(rows["filter"]), "population": strings(rows["population"]),
                    "percentile": np.asarray(rows["percentile"], np.int64 if integral else float)}  # fmt: skip
    out.update({name: np.asarray(rows[name], float) for name in ERROR_NAMES})
    out.update({name: np.asarray(rows[name], np.int64) for name in counts})
    return out


def wilson_interval(k: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """The Wilson score interval of a rate ``k / n`` (``scipy.stats.binomtest``); ``(nan, nan)`` for ``n = 0``."""
    if n <= 0:
        return float("nan"), float("nan")
    from scipy.stats import binomtest

    ci = binomtest(int(k), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


def rate_text(k: int, n: int, interval: bool = True) -> str:
    """``"72 of 100 (72 %, 95 % CI 62-80 %)"``: a count, its rate and the rate's Wilson interval.

    ``interval=False``: without the interval (``"72 of 100 (72 %)"``), for the run path, which does not import
    scipy.stats (it imports scipy.linalg: ~0.2 s of a small run; tests/outputs/test_arrow.py).
    """
    if n <= 0:
        return "0 of 0"
    if not interval:
        return f"{k} of {n} ({100 * k / n:.0f} %)"
    lo, hi = wilson_interval(k, n)
    return f"{k} of {n} ({100 * k / n:.0f} %, 95 % CI {100 * lo:.0f}-{100 * hi:.0f} %)"


def percentile_table(trials: Any, percentiles: list[float], exclude_inconsistent: bool = False) -> pd.DataFrame:
    """:func:`percentile_columns` as a DataFrame (for the report, the studies and the docs)."""
    import pandas as pd

    return pd.DataFrame(percentile_columns(trials, percentiles, exclude_inconsistent))


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
    g = (c["filter"] == label) & ~excluded(c)
    out = {}
    for name in ("k1", "k2"):
        col = f"final_sigma_ratio_{name}"
        v = c[col][g].astype(float) if col in c else np.empty(0)
        v = v[~np.isnan(v)]
        if v.size and float(np.median(v)) > UNOBSERVABLE_RATIO:
            out[name] = float(np.median(v))
    return out


def reason_kind(reason: str) -> str:
    """A lost or inconsistency reason without its numbers, to group trials by kind:
    ``inconsistent: gauge-projected NEES >= 1.3e+06 over 10 steps > ...`` -> ``inconsistent: gauge-projected NEES``,
    ``error bound exceeded: e_rho = 1.2e3 > 1000`` -> ``error bound exceeded: e_rho``."""
    r = str(reason).split(" = ", 1)[0]
    for sep in (" >= ", " over ", " x its", " > "):
        r = r.split(sep, 1)[0]
    return r.strip() or "(no reason recorded)"


def reasons_by_kind(c: Columns, rows: np.ndarray, column: str) -> dict[str, list[int]]:
    """The trial ids of ``rows`` (a mask) per kind of their ``column`` reason, the most frequent kind first."""
    by: dict[str, list[int]] = {}
    for trial, reason in zip(c["trial"][rows].tolist(), c[column][rows]):
        by.setdefault(reason_kind(reason), []).append(int(trial))
    return dict(sorted(by.items(), key=lambda kv: (-len(kv[1]), kv[0])))


def population_note(trials: Any, label: str, exclude_inconsistent: bool = False) -> str:
    """Which trials the two populations hold: the ids left out of ``converged`` (the lost ones), by kind of
    reason, and the inconsistent ones (counted unless ``exclude_inconsistent``)."""
    c = columns_of(trials)
    f = c["filter"] == label
    lost = f & excluded(c)
    incons = f & np.asarray(c["inconsistent"]).astype(bool) if "inconsistent" in c else np.zeros(f.size, bool)
    lines = []

    def listed(by: dict[str, list[int]]) -> None:
        for kind, ids in by.items():
            ids = sorted(ids)
            shown = ", ".join(map(str, ids[:30])) + (f", ... ({len(ids) - 30} more)" if len(ids) > 30 else "")
            lines.append(f"- {kind} ({len(ids)}): {shown}")

    if lost.any():
        lines.append("`converged` (the trials not lost) leaves out these lost trials (`all` holds them as +inf):\n")
        listed(reasons_by_kind(c, lost, "lost_reason" if "lost_reason" in c else "diverged_reason"))
    else:
        lines.append("No trial was lost.")
    if incons.any():
        how = ("left out of `converged` too (`divergence.exclude_inconsistent: true`)" if exclude_inconsistent
               else "a truth-based flag only: it did not stop the filter, and the errors of those not lost count")  # fmt: skip
        lines.append(f"\nInconsistent trials, {how}:\n")
        listed(reasons_by_kind(c, incons, "inconsistent_reason"))
    return "\n".join(lines) + "\n"


def percentiles_markdown(pt: Any, trials: Any = None, exclude_inconsistent: bool = False,
                         interval: bool = False) -> str:  # fmt: skip
    """The percentile tables per filter with the counts and rates (``interval``: with their Wilson intervals)."""
    c = columns_of(pt)
    out = []
    for label in dict.fromkeys(c["filter"].tolist()):
        rows = np.flatnonzero(c["filter"] == label)
        i = int(rows[0])
        n = int(c["trials"][i])
        kept = int(c["trials"][rows[c["population"][rows] == "converged"][0]]) if "population" in c else n
        nl = int(c["lost"][i]) if "lost" in c else int(c["diverged"][i])
        head = f"## {label}: {kept} of {n} trials in the statistics; lost: {rate_text(nl, n, interval)}"
        if "inconsistent" in c:
            head += f"; inconsistent: {rate_text(int(c['inconsistent'][i]), n, interval)}"
        out.append(head + "\n")
        if trials is not None:
            out.append(population_note(trials, label, exclude_inconsistent))
            for name, m in not_observable(trials, label).items():
                out.append(f"{name}: not observable in this run (median final sigma = {m:.2f} x the initial one; "
                           "carried with its covariance, not a failure).\n")
        what = "not lost nor inconsistent" if exclude_inconsistent else "not lost"
        out.append(f"Trials {what} ({kept}):\n\n" + format_table(c, label, "converged", markdown=True) + "\n")
        out.append(f"All trials ({n}; a lost trial counts as +inf):\n\n"
                   + format_table(c, label, "all", markdown=True) + "\n")  # fmt: skip
    return "\n".join(out)
