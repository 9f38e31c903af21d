"""The answers a report leads with: per filter, how many trials converged, why the others
diverged, the typical errors, and whether the filter is consistent, in words.

Consistency from the columns every run has:

- **NEES**: ``nees_mean`` of ``trials.parquet`` (each trial's mean NEES over the error
  window). For a consistent filter each step's NEES is chi-square with ``d = n - 1``
  degrees of freedom (``n`` = state dimension; the unit quaternion takes one direction
  out), so the average over ``N`` converged trials lies in the two-sided 95 % band
  ``chi2.ppf([0.025, 0.975], N d) / N``. A trial's window mean averages correlated steps,
  which only narrows its spread: this band is the widest (most lenient) one, so an
  average outside it is a clear verdict.
- **NIS**: from ``timeseries.parquet`` when present, each trial's mean over the window of
  ``nis / nis_dof`` (the NIS per measurement dimension, 1 for a consistent filter),
  averaged over the trials, against ``chi2.ppf([0.025, 0.975], N m) / (N m)`` with ``m``
  the median measurement dimension.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.special import chdtri  # chi2.ppf(p, k) = chdtri(k, 1 - p), without importing scipy.stats

LEVEL = 0.95


@dataclass(frozen=True)
class Check:
    """One consistency statistic against its band: the average, the band, and the verdict."""

    what: str  # "NEES" / "NIS per dimension"
    value: float
    expected: float
    lo: float
    hi: float
    trials: int
    dof: float
    median: float = float("nan")  # the median trial's value: a few wild trials move the average, not this

    @property
    def state(self) -> str:
        if not np.isfinite(self.value):
            return "unknown"
        return "high" if self.value > self.hi else "low" if self.value < self.lo else "inside"

    def words(self) -> str:
        band = f"95 % band [{self.lo:.3g}, {self.hi:.3g}] for a consistent filter over {self.trials} trials"
        avg = f"average {self.what} {self.value:.3g} (expected {self.expected:.3g}; median trial {self.median:.3g})"
        if self.state == "inside":
            return f"{avg} is inside the {band}"
        if self.state == "high":
            return (f"{avg} is {self.value / self.expected:.3g} times too large, above the {band}: the filter is "
                    "overconfident, its covariance understates the actual errors")  # fmt: skip
        if self.state == "low":
            return (f"{avg} is below the {band}: the filter is conservative, its covariance overstates the "
                    "actual errors")  # fmt: skip
        return f"{self.what}: no finite values"


def band(trials: int, dof: float, level: float = LEVEL) -> tuple[float, float]:
    """Two-sided ``level`` band of the mean of ``trials`` chi-square(``dof``) variables."""
    if trials < 1 or not dof > 0:
        return float("nan"), float("nan")
    a = 1.0 - level
    k = trials * dof
    return float(chdtri(k, 1 - a / 2) / trials), float(chdtri(k, a / 2) / trials)


def nees_check(g: pd.DataFrame, state_dim: int | None) -> Check | None:
    if not state_dim or "nees_mean" not in g:
        return None
    v = g.loc[~g["diverged"].astype(bool), "nees_mean"].to_numpy(float)
    v = v[np.isfinite(v)]
    d = state_dim - 1
    lo, hi = band(v.size, d)
    nan = float("nan")
    return Check("NEES", float(v.mean()) if v.size else nan, float(d), lo, hi, int(v.size), float(d),
                 float(np.median(v)) if v.size else nan)  # fmt: skip


def nis_check(ts: pd.DataFrame | None, label: str, ok_trials: set[int], window_start: float | None) -> Check | None:
    if ts is None or ts.empty or "nis_dof" not in ts:
        return None
    g = ts[(ts["filter"] == label) & (ts["nis_dof"] > 0) & ts["trial"].isin(ok_trials)]
    if window_start is not None:
        g = g[g["t"] >= window_start - 1e-9]
    g = g[np.isfinite(g["nis"])]
    if g.empty:
        return None
    per_trial = (g["nis"] / g["nis_dof"]).groupby(g["trial"]).mean().to_numpy(float)
    m = float(np.median(g["nis_dof"]))
    lo, hi = band(per_trial.size, m)
    return Check("NIS per dimension", float(per_trial.mean()), 1.0, lo / m, hi / m, int(per_trial.size), m,
                 float(np.median(per_trial)))  # fmt: skip


@dataclass
class FilterSummary:
    label: str
    kind: str
    trials: int
    diverged: int
    reasons: list[tuple[str, int]] = field(default_factory=list)
    checks: list[Check] = field(default_factory=list)

    @property
    def converged(self) -> int:
        return self.trials - self.diverged

    @property
    def consistent(self) -> bool | None:
        """True / False when every / some available check says so; None without any."""
        known = [c for c in self.checks if c.state != "unknown"]
        return None if not known else all(c.state == "inside" for c in known)

    def verdict(self) -> str:
        """One sentence: the consistency verdict in words."""
        if self.consistent is None:
            return "consistency unknown: no NEES or NIS values"
        bad = [c for c in self.checks if c.state in ("high", "low")]
        if not bad:
            return "consistent: " + "; ".join(c.words() for c in self.checks)
        return "NOT consistent: " + "; ".join(c.words() for c in bad)

    def divergence_words(self) -> str:
        if not self.diverged:
            return "no trial diverged"
        top = ", ".join(f"{reason} ({n})" for reason, n in self.reasons[:3])
        more = f", {len(self.reasons) - 3} other reason(s)" if len(self.reasons) > 3 else ""
        return f"{self.diverged} diverged: {top}{more}"


def summarize(trials: pd.DataFrame, timeseries: pd.DataFrame | None, filters: list[str], types: dict[str, str],
              state_dim: int | None, window_start: float | None, reason_of) -> list[FilterSummary]:  # fmt: skip
    """One :class:`FilterSummary` per filter; ``reason_of`` maps a reason to its category."""
    out = []
    for label in filters:
        g = trials[trials["filter"] == label]
        div = g["diverged"].astype(bool)
        reasons: list[tuple[str, int]] = []
        if div.any() and "diverged_reason" in g:
            counts = g.loc[div, "diverged_reason"].astype(str).map(reason_of).value_counts()
            reasons = [(str(k), int(v)) for k, v in counts.items()]
        s = FilterSummary(label, types.get(label, "?"), len(g), int(div.sum()), reasons)
        ok = set(int(t) for t in g.loc[~div, "trial"])
        s.checks = [c for c in (nees_check(g, state_dim), nis_check(timeseries, label, ok, window_start)) if c]
        out.append(s)
    return out
