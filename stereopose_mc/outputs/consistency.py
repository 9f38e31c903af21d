"""Consistency of a filter over a run: NEES per block and gauge-projected, NIS, in words.

Reads the per-trial window means of ``trials.parquet`` (``nees_mean``, ``nees_<block>_mean``,
``nees_gauge_mean``, ``nis_ratio_mean``) and summarizes them per filter over the trials
that were not lost: the median over trials of the time-averaged NEES divided by its
degrees of freedom (one convention everywhere, docs/filters.md: the error state has
``n - 1`` dimensions, the gauge-projected one ``n - 4``), and the median time-averaged
NIS per measurement dimension against the chi-square 95 % band of one trial's average.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.special import chdtri

from ..core import errorstate as es
from ..rundir.percentiles import excluded

NEES_LIMIT = 2.0  # a median NEES/dof above this is called overconfident (issue 10's target)


@dataclass(frozen=True)
class Consistency:
    """One filter's consistency over the converged trials of a run."""

    label: str
    trials: int
    nees: dict[str, float]  # median NEES/dof per key of errorstate.nees_dof
    dof: dict[str, int]
    nis_ratio: float  # median time-averaged NIS / dof
    nis_band: tuple[float, float]  # 95 % chi-square band of one trial's time average / dof

    @property
    def overconfident(self) -> list[str]:
        return [k for k, v in self.nees.items() if np.isfinite(v) and v > NEES_LIMIT]

    @property
    def nis_inside(self) -> bool:
        return bool(self.nis_band[0] <= self.nis_ratio <= self.nis_band[1])

    @property
    def consistent(self) -> bool:
        return not self.overconfident and self.nis_inside

    def verdict(self) -> str:
        """The finding in words, with the numbers."""
        g, full = self.nees.get("nees_gauge", np.nan), self.nees.get("nees", np.nan)
        head = (f"{self.label}, over {self.trials} trials not lost: median time-averaged NEES/dof {g:.3g} gauge-projected ({self.dof['nees_gauge']} dof), "
                f"{full:.3g} full ({self.dof['nees']} dof); NIS/dof {self.nis_ratio:.3g} "
                f"(95 % band {self.nis_band[0]:.3g}-{self.nis_band[1]:.3g})")
        if self.consistent:
            return head + ": consistent."
        bad = []
        if self.overconfident:
            worst = max(self.overconfident, key=lambda k: self.nees[k])
            bad.append(f"overconfident in {', '.join(_name(k) for k in self.overconfident)} (worst "
                       f"{_name(worst)}: {self.nees[worst]:.3g} x its dof, limit {NEES_LIMIT:g})")
        if not self.nis_inside:
            side = "above" if self.nis_ratio > self.nis_band[1] else "below"
            edge = self.nis_band[1 if side == "above" else 0]
            bad.append(f"NIS/dof {self.nis_ratio:.4g} {side} its band's {'upper' if side == 'above' else 'lower'} end "
                       f"{edge:.4g}")  # fmt: skip
        return head + ": NOT consistent: " + "; ".join(bad) + "."


def _name(key: str) -> str:
    return {"nees": "the full state", "nees_gauge": "the gauge-projected state"}.get(key, key.removeprefix("nees_"))


def nis_band(dof_mean: float, steps: int, level: float = 0.95) -> tuple[float, float]:
    """Two-sided band of a time average over ``steps`` steps of NIS/dof with ``dof_mean`` rows each."""
    d = max(1.0, dof_mean * steps)
    lo, hi = chdtri(d, [(1 + level) / 2, (1 - level) / 2]) / d  # chi2.ppf([0.025, 0.975], d) / d
    return float(lo), float(hi)


def summarize(trials: pd.DataFrame, label: str, state_dim: int, window_steps: int) -> Consistency:
    """Consistency of filter ``label`` from a trials table (converged trials only)."""
    g = trials[(trials["filter"] == label).to_numpy() & ~excluded(tables_cols(trials))]
    dof = es.nees_dof(state_dim)
    med = {}
    for k, d in dof.items():
        col = f"{k}_mean"
        per_trial = f"dof_{k}"  # the window's mean dof per trial (feature slots: occupied ones only)
        dk = g[per_trial].to_numpy(float) if per_trial in g else d
        v = g[col].to_numpy(float) / dk if col in g else np.array([])
        v = v[np.isfinite(v)]
        med[k] = float(np.median(v)) if v.size else float("nan")
    r = g["nis_ratio_mean"].to_numpy(float) if "nis_ratio_mean" in g else np.array([])
    r = r[np.isfinite(r)]
    dm = g["nis_dof_mean"].to_numpy(float) if "nis_dof_mean" in g else np.array([])
    m = float(dm[np.isfinite(dm)].mean()) if np.isfinite(dm).any() else (float("nan") if dm.size else 1.0)
    return Consistency(label, len(g), med, dof, float(np.median(r)) if r.size else float("nan"),
                       nis_band(m, window_steps))  # fmt: skip


def tables_cols(trials: pd.DataFrame) -> dict:
    """The flag columns of a trials table, as ``rundir.percentiles.excluded`` reads them."""
    return {c: trials[c].to_numpy() for c in ("lost", "diverged", "inconsistent") if c in trials}


def table(cs: list[Consistency]) -> pd.DataFrame:
    """One row per filter: median NEES/dof per block, gauge-projected, NIS/dof and its band."""
    rows = []
    for c in cs:
        row = {"filter": c.label, "trials": c.trials}
        row.update({k: v for k, v in c.nees.items()})
        row.update(nis=c.nis_ratio, nis_lo=c.nis_band[0], nis_hi=c.nis_band[1], consistent=c.consistent)
        rows.append(row)
    return pd.DataFrame(rows)
