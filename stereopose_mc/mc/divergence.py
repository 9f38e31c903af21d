"""The ``inconsistent`` divergence rule: a trial whose filter claims far less error than it has.

Two tests over the last ``window`` steps (all at or after ``start_s``), per trial:

- **block**: for a block ``b`` of the error state (rho, rho_dot, omega, attitude, feature
  points, k), the error in claimed standard deviations ``sqrt(NEES_b / dof_b)`` stays above
  ``sigma_ratio`` at every step of the window (a k error of 6.4 against a claimed sigma of
  0.05 is 128 sigma);
- **gauge**: the gauge-projected NEES stays above ``nees_factor`` times the chi-square
  99.9 % bound of its ``n - 4`` degrees of freedom at every step of the window.

Such a trial is not counted as converged: its reason starts with ``inconsistent``.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
CHI2_TABLE = Path(__file__).resolve().parents[1] / "data" / "chi2_999.csv"


@functools.lru_cache(maxsize=1)
def _chi2_table() -> dict[int, float]:
    """``dof -> chi2.ppf(0.999, dof)`` for dof 1-1000, as scipy's ``chdtri(dof, 0.001)`` gives it, bit for bit
    (``tests/mc/test_divergence.py`` checks every value; ``write_chi2_table`` writes the file)."""
    rows = CHI2_TABLE.read_text(encoding="utf-8").split()[1:]
    return {int(d): float(v) for d, v in (r.split(",") for r in rows)}


@functools.lru_cache(maxsize=64)
def chi2_999(dof: int) -> float:
    """``chi2.ppf(0.999, dof)``: from the table (importing scipy.special costs 0.03-0.15 s of a run), else scipy."""
    v = _chi2_table().get(int(dof))
    if v is not None:
        return v
    from scipy.special import chdtri  # chi-square inverse survival function (scipy.stats costs ~0.2 s to import)

    return float(chdtri(dof, 0.001))


def write_chi2_table(path: Path = CHI2_TABLE, max_dof: int = 1000) -> None:
    """(Re)write the table of ``chi2_999`` from scipy (floats as ``repr``: exact)."""
    from scipy.special import chdtri

    rows = ["dof,chi2_ppf_0999"] + [f"{d},{float(chdtri(d, 0.001))!r}" for d in range(1, max_dof + 1)]
    Path(path).write_text("\n".join(rows) + "\n", encoding="utf-8")


def inconsistent_reasons(parts: dict[str, Array], rows: Array, w0: int, k: int, dof: dict[str, int | Array],
                         sigma_ratio: float, nees_factor: float,
                         minima: dict[str, Array] | None = None) -> list[str]:  # fmt: skip
    """Reason per row of ``rows`` ('' when consistent enough) from NEES histories ``(B, K+1)``.

    ``dof[name]``: the NEES's degrees of freedom, one number, or ``(B, K+1)`` per trial and step (feature slots:
    only the occupied slots count, ``filters.slots.nees``); a step with 0 dof does not test. ``minima[name]``: the
    window's minimum of each row, ``np.min(parts[name][rows, w0 : k + 1], axis=1)``, where the caller has them (the
    NEES of a step in one array: one pass for all); read for the names with one number of dof, whose tests depend
    on the window through its minimum only (the minimum of ``NEES / dof`` is that of the NEES over ``dof``: the
    same bits, division by a positive number being monotonic after rounding).
    """
    reasons = [""] * rows.size
    with np.errstate(invalid="ignore", divide="ignore"):
        for name, a in parts.items():
            d = dof[name] if np.isscalar(dof[name]) else dof[name][rows, w0 : k + 1]
            if np.isscalar(d):
                low = minima[name] if minima is not None else np.min(a[rows, w0 : k + 1], axis=1)
                if name == "nees_gauge":
                    bad = low > nees_factor * chi2_999(d)  # every step of the window above the bound
                elif name.startswith("nees_"):
                    sig = np.sqrt(low / d)
            else:
                win = a[rows, w0 : k + 1]
                if name == "nees_gauge":
                    bound = nees_factor * np.vectorize(chi2_999, otypes=[float])(np.maximum(d, 1))
                    low = np.min(win, axis=1)
                    bad = np.all(win > bound, axis=1)
                elif name.startswith("nees_"):
                    sig = np.sqrt(np.min(np.where(d > 0, win / np.maximum(d, 1), np.inf), axis=1))
            if name == "nees_gauge":
                for j in np.flatnonzero(bad):
                    dj = d if np.isscalar(d) else int(np.min(d[j]))
                    reasons[j] = reasons[j] or (f"inconsistent: gauge-projected NEES >= {low[j]:.3g} over "
                                                f"{k - w0 + 1} steps > {nees_factor:g} x chi2 99.9% bound "
                                                f"{chi2_999(dj):.3g} ({dj} dof)")  # fmt: skip
            elif name.startswith("nees_"):
                for j in np.flatnonzero(np.isfinite(sig) & (sig > sigma_ratio)):
                    reasons[j] = reasons[j] or (f"inconsistent: {name[5:]} error >= {sig[j]:.3g} x its claimed "
                                                f"sigma over {k - w0 + 1} steps > {sigma_ratio:g}")  # fmt: skip
    return reasons
