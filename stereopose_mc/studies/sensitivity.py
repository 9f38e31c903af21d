"""What drives the error: sensitivity of a dispersed campaign's metrics to its dispersed scalars.

For every filter, every error metric (the per-trial window means ``e_rho`` ... ``e_k2`` of
the trials that converged) and every dispersed scalar (a ``trials.parquet`` column named
after its key path):

- Spearman's rank correlation (``scipy.stats.spearmanr``) with a 95 % confidence interval
  from Fisher's z with the Fieller-Hartley-Pearson standard error ``sqrt(1.06 / (n - 3))``,
  its p-value, and whether it is significant after a Bonferroni correction over all the
  pairs of that filter;
- divergence as a metric: the rank-biserial correlation ``r = 1 - 2U / (n1 n2)`` of each
  scalar between diverged and converged trials (``scipy.stats.mannwhitneyu``), positive
  when diverged trials have larger values;
- for ``sampling: sobol`` campaigns, first-order and total Sobol indices of every input
  factor (``SALib.analyze.sobol``, on the complete Saltelli blocks); for a metric with
  diverged trials in the design, of its rank with the diverged trials tied at the worst
  (``rank(e_rho)``: the "all trials, diverged = +inf" view of the percentile tables).

Invalid draws (``invalid``) are left out of every statistic and counted. In a ``sobol``
campaign the correlations use only the design's independent rows (A and B of each block).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import stats

from ..config.schema import Scenario
from ..rundir.tables import ERROR_NAMES
from ..sim import dispersions as sd

DIVERGED = "diverged"
METRICS = (*ERROR_NAMES, DIVERGED)
Z95 = float(stats.norm.ppf(0.975))


def parameter_columns(trials: pd.DataFrame, scn: Scenario) -> list[str]:
    """The dispersed-scalar columns of a run's trials table that vary, in table order."""
    if scn.dispersions is None:
        return []
    paths = list(scn.dispersions.specs)
    cols = [c for c in trials.columns if any(c == p or c.startswith(p + "[") or c == f"|{p}|" for p in paths)]
    return [c for c in cols if trials[c].nunique() > 1]


def spearman_ci(rho: float, n: int) -> tuple[float, float]:
    """95 % interval of Spearman's rho: Fisher z, standard error sqrt(1.06 / (n - 3))."""
    if n <= 4 or not np.isfinite(rho):
        return np.nan, np.nan
    z = np.arctanh(np.clip(rho, -0.999999, 0.999999))
    se = np.sqrt(1.06 / (n - 3))
    return float(np.tanh(z - Z95 * se)), float(np.tanh(z + Z95 * se))


@dataclass
class Sensitivity:
    table: pd.DataFrame  # filter, metric, parameter, statistic, value, ci_low, ci_high, p, n, significant
    sobol: pd.DataFrame | None = None  # filter, metric, factor, S1, S1_conf, ST, ST_conf
    notes: list[str] = field(default_factory=list)
    invalid: int = 0


def correlations(trials: pd.DataFrame, params: list[str]) -> pd.DataFrame:
    """Spearman (errors) and rank-biserial (divergence) of every filter x metric x parameter."""
    rows = []
    for label, g in trials.groupby("filter", sort=False):
        div = g["diverged"].to_numpy(bool)
        for metric in METRICS:
            for p in params:
                x = g[p].to_numpy(float)
                if metric == DIVERGED:
                    n1, n0 = int(div.sum()), int((~div).sum())
                    if n1 == 0 or n0 == 0:
                        continue
                    u = stats.mannwhitneyu(x[div], x[~div], alternative="two-sided")
                    r = 1.0 - 2.0 * u.statistic / (n1 * n0)
                    r = -r  # positive: the diverged trials have the larger values
                    rows.append((label, metric, p, "rank-biserial", r, np.nan, np.nan, float(u.pvalue), n1 + n0))
                    continue
                y = g[metric].to_numpy(float)
                ok = ~div & np.isfinite(y) & np.isfinite(x)
                n = int(ok.sum())
                if n < 5 or np.ptp(x[ok]) == 0 or np.ptp(y[ok]) == 0:
                    continue
                res = stats.spearmanr(x[ok], y[ok])
                lo, hi = spearman_ci(float(res.statistic), n)
                rows.append((label, metric, p, "spearman", float(res.statistic), lo, hi, float(res.pvalue), n))
    cols = ["filter", "metric", "parameter", "statistic", "value", "ci_low", "ci_high", "p", "n"]
    df = pd.DataFrame(rows, columns=cols)
    m = df.groupby("filter")["p"].transform("size") if len(df) else pd.Series(dtype=float)
    df["significant"] = df["p"] < 0.05 / m if len(df) else pd.Series(dtype=bool)
    return df


def drivers(table: pd.DataFrame, label: str, top: int = 3) -> pd.DataFrame:
    """The ``top`` parameters with the largest |statistic| per metric of one filter (ranked)."""
    g = table[table["filter"] == label].copy()
    g["abs"] = g["value"].abs()
    g = g.sort_values(["metric", "abs"], ascending=[True, False], kind="stable")
    g["rank"] = g.groupby("metric").cumcount() + 1
    order = {m: i for i, m in enumerate(METRICS)}
    g = g[g["rank"] <= top].sort_values(["metric", "rank"], key=lambda s: s.map(order) if s.name == "metric" else s)
    return g.drop(columns="abs").reset_index(drop=True)


def sobol_indices(trials: pd.DataFrame, scn: Scenario) -> tuple[pd.DataFrame | None, list[str]]:
    """First-order and total Sobol indices per filter and metric (SALib), for ``sampling: sobol`` runs."""
    from SALib.analyze import sobol as sobol_analyze

    names = sd.factor_names(scn)
    D = len(names)
    n_blocks = scn.trials // (D + 2)
    notes: list[str] = []
    if n_blocks < 2:
        return None, [f"Sobol indices need at least 2 complete Saltelli blocks of D + 2 = {D + 2} trials "
                      f"(this run has {scn.trials} trials)"]  # fmt: skip
    used = n_blocks * (D + 2)
    if used < scn.trials:
        notes.append(f"Sobol indices use the first {used} trials ({n_blocks} complete blocks of {D + 2})")
    if n_blocks & (n_blocks - 1):
        notes.append(f"{n_blocks} Saltelli base points is not a power of 2: the Sobol' sequence's balance is lost")
    problem = {"num_vars": D, "names": [f"f{i}" for i in range(D)], "bounds": [[0.0, 1.0]] * D}
    rows = []
    for label, g in trials.groupby("filter", sort=False):
        g = g.sort_values("trial")
        g = g[g["trial"] < used]
        if len(g) != used:
            notes.append(f"{label}: Sobol indices skipped (trials missing from the design)")
            continue
        if g["invalid"].any() if "invalid" in g else False:
            notes.append(f"{label}: Sobol indices skipped ({int(g['invalid'].sum())} invalid draws in the design)")
            continue
        for metric in METRICS:
            y = g["diverged"].to_numpy(float) if metric == DIVERGED else g[metric].to_numpy(float)
            name_m = metric
            if not np.all(np.isfinite(y)):
                # the error's rank, diverged trials tied at the worst (as +inf in the "all" percentiles)
                n_bad = int((~np.isfinite(y)).sum())
                y = stats.rankdata(np.where(np.isfinite(y), y, np.inf)) / y.size
                name_m = f"rank({metric})"
                notes.append(f"{label}: {n_bad} trials of the design diverged: the Sobol indices of {metric} are "
                             f"those of its rank with the diverged trials ranked worst ({name_m})")  # fmt: skip
            if np.ptp(y) == 0:
                continue
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                si = sobol_analyze.analyze(problem, y, calc_second_order=False, seed=scn.seed)
            for i, name in enumerate(names):
                rows.append((label, name_m, name, si["S1"][i], si["S1_conf"][i], si["ST"][i], si["ST_conf"][i]))
    df = pd.DataFrame(rows, columns=["filter", "metric", "factor", "S1", "S1_conf", "ST", "ST_conf"])
    return (df if len(df) else None), notes


def analyze(trials: pd.DataFrame, scn: Scenario) -> Sensitivity | None:
    """The sensitivity analysis of a run (``None`` when it has no dispersed scalars)."""
    params = parameter_columns(trials, scn)
    if not params:
        return None
    invalid = trials["invalid"].to_numpy(bool) if "invalid" in trials else np.zeros(len(trials), bool)
    valid = trials[~invalid]
    sobol = scn.dispersions is not None and scn.dispersions.sampling == "sobol"
    notes = []
    if sobol:  # correlations on the independent rows only: A and B of each Saltelli block
        D2 = len(sd.factor_names(scn)) + 2
        r = valid["trial"].to_numpy() % D2
        valid = valid[(r == 0) | (r == D2 - 1)]
        notes.append(f"Sobol design: the correlations use its {valid['trial'].nunique()} independent rows (A and B "
                     f"of each Saltelli block); the AB rows share all but one coordinate and the noise with A")
    out = Sensitivity(correlations(valid, params), invalid=int(trials.loc[invalid, "trial"].nunique()), notes=notes)
    if sobol:
        out.sobol, more = sobol_indices(trials, scn)
        out.notes += more
    return out
