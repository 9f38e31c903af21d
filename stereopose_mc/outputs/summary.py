"""The answers a report leads with, per filter (docs/outputs.md, The report):

- how many trials were **lost** (the filter's own tests stopped it) and how many were flagged
  **inconsistent** (truth-based; the filter ran on and its errors count), each as a rate with
  its 95 % Wilson interval (``rundir.percentiles.wilson_interval``), and why, grouped by kind;
- the accuracy: the 50th and 90th percentiles of each per-trial mean error over the trials in
  the statistics (not lost; nor inconsistent with ``divergence.exclude_inconsistent``), with
  their count;
- one consistency verdict in words naming the blocks that fail (``outputs.consistency``:
  median time-averaged NEES per degree of freedom of the full, gauge-projected and block error
  states, and the NIS per measurement dimension against its band);
- what to try when most trials are lost (:func:`remedies`).

The NEES band of the mean over ``N`` trials (:func:`band`) is also what the figures over time draw.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..rundir import percentiles as pct
from ..rundir.tables import columns_of

LEVEL = 0.95


def band(trials: int, dof: float, level: float = LEVEL) -> tuple[float, float]:
    """Two-sided ``level`` band of the mean of ``trials`` chi-square(``dof``) variables."""
    from scipy.special import chdtri  # chi2.ppf(p, k) = chdtri(k, 1 - p), without importing scipy.stats

    if trials < 1 or not dof > 0:
        return float("nan"), float("nan")
    a = 1.0 - level
    k = trials * dof
    return float(chdtri(k, 1 - a / 2) / trials), float(chdtri(k, a / 2) / trials)


@dataclass
class FilterSummary:
    label: str
    kind: str
    trials: int
    lost: int
    inconsistent: int
    kept: int  # trials in the accuracy statistics
    lost_kinds: list[tuple[str, int]] = field(default_factory=list)
    inconsistent_kinds: list[tuple[str, int]] = field(default_factory=list)
    lost_median_step: float = float("nan")  # the median step at which the lost trials were lost

    def rate(self, k: int) -> str:
        return pct.rate_text(k, self.trials)

    def kinds_words(self, kinds: list[tuple[str, int]], top: int = 3) -> str:
        shown = ", ".join(f"{k} ({n})" for k, n in kinds[:top])
        return shown + (f", {len(kinds) - top} other kind(s)" if len(kinds) > top else "")


def summarize(trials: Any, filters: list[str], types: dict[str, str],
              exclude_inconsistent: bool = False) -> list[FilterSummary]:  # fmt: skip
    """One :class:`FilterSummary` per filter from a trials table (a DataFrame, a pyarrow Table or columns: the run
    path imports no pandas) with its ``lost*`` and ``inconsistent*`` columns (the ``diverged*`` aliases of older
    runs are read as ``lost*``)."""
    c = columns_of(trials)
    pre = "lost" if "lost" in c else "diverged"
    lost_all = pct.excluded(c)
    inc_all = np.asarray(c["inconsistent"]).astype(bool) if "inconsistent" in c else np.zeros(lost_all.size, bool)
    out = []
    for label in filters:
        g = np.asarray(c["filter"]) == label
        lost, inc = lost_all & g, inc_all & g
        kept = int((g & ~(lost | (inc & exclude_inconsistent))).sum())
        step = float(np.median(c[f"{pre}_step"][lost])) if lost.any() and f"{pre}_step" in c else float("nan")
        kinds = [(k, len(v)) for k, v in pct.reasons_by_kind(c, lost, f"{pre}_reason").items()] \
            if lost.any() and f"{pre}_reason" in c else []  # fmt: skip
        ikinds = [(k, len(v)) for k, v in pct.reasons_by_kind(c, inc, "inconsistent_reason").items()] \
            if inc.any() else []  # fmt: skip
        out.append(FilterSummary(label, types.get(label, "?"), int(g.sum()), int(lost.sum()), int(inc.sum()), kept,
                                 kinds, ikinds, step))  # fmt: skip
    return out


def remedies(s: FilterSummary, filter_config: dict | None) -> list[str]:
    """What went wrong for a filter that lost most of its trials, and the documented remedies (docs/filters.md)."""
    if s.trials == 0 or 2 * s.lost <= s.trials:
        return []
    cfg = filter_config or {}
    top = s.lost_kinds[0][0] if s.lost_kinds else ""
    out = []
    when = f" (median lost step {s.lost_median_step:g})" if np.isfinite(s.lost_median_step) else ""
    if top.startswith("filter lost: no feature measured"):
        out.append(f"{s.label} loses {s.lost} of {s.trials} trials{when} because its cameras measured no feature "
                   "for a whole window: check the camera's field of view and range, the feature points (inside the "
                   "body, hidden by occlusion?) and the tracker's dropouts; `spmc validate` warns when no feature is "
                   "ever in view.")  # fmt: skip
    elif top.startswith("filter lost: its gate rejected"):
        out.append(f"{s.label} loses {s.lost} of {s.trials} trials{when} to its own gate (it rejected most features "
                   "for a whole window): the measurement noise or the process noise is too small for the actual "
                   "errors, or the gate too tight; try a larger `gating.probability`, `process_noise`, or check "
                   "`measurements`; docs/filters.md.")  # fmt: skip
    elif cfg.get("type") in ("ekf", "mekf") and cfg.get("first_update", "ekf") != "iterated" \
            and not cfg.get("iterated"):
        out.append(f"{s.label} loses {s.lost} of {s.trials} trials{when}, mostly '{top}': from a wide prior its "
                   "single-step first update linearizes far from the truth and it does not recover. Try "
                   "`first_update: iterated` on this filter (its first update iterated as the IEKF's) or "
                   "`initial_estimate: measurements` (start from the first stereo frame); docs/filters.md.")  # fmt: skip
    elif top:
        out.append(f"{s.label} loses {s.lost} of {s.trials} trials{when}, mostly '{top}'; docs/filters.md (Lost and "
                   "inconsistent trials) lists what each reason means.")  # fmt: skip
    return out
