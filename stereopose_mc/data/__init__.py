"""Reference data bundled with the package: the seed thesis's percentile tables.

``thesis_percentiles.csv`` holds Tables 6.1-6.6 of the thesis (cases A-F): percentiles
50/70/90/100 over 100 IEKF trials of the per-trial mean estimation error over
``t >= 10 s``; units rho m, rho_dot m/s, omega deg/s, theta deg, k1 and k2 dimensionless.
"""

from __future__ import annotations

import io
import re
from functools import lru_cache
from importlib import resources

import pandas as pd

# Column of the bundled CSV -> the error column name used by run directories.
THESIS_COLUMNS = {"rho_m": "e_rho", "rho_dot_mps": "e_rho_dot", "omega_degps": "e_omega",
                  "theta_deg": "e_theta", "k1": "e_k1", "k2": "e_k2"}  # fmt: skip
THESIS_TABLE_NUMBER = {c: f"6.{i + 1}" for i, c in enumerate("ABCDEF")}
# Thesis Table 6.7: IEKF computation time per trial, case B (200 runs, MATLAB on an Intel Xeon E5-2609 2.5 GHz).
THESIS_COMPUTE_TIME_CASE_B_S = {"max": 8.5, "mean": 7.4, "min": 6.89}

_CASE_RE = re.compile(r"^case([A-F])(?:[-_.].*)?$")


def thesis_case(scenario_name: str) -> str | None:
    """The thesis case letter of a scenario name: ``caseB`` and ``caseB-small`` -> ``'B'``; else ``None``."""
    m = _CASE_RE.match(scenario_name or "")
    return m.group(1) if m else None


@lru_cache(maxsize=1)
def _raw() -> pd.DataFrame:
    text = resources.files(__package__).joinpath("thesis_percentiles.csv").read_text(encoding="utf-8")
    return pd.read_csv(io.StringIO(text), comment="#")


def thesis_percentiles(case: str | None = None) -> pd.DataFrame:
    """The thesis's percentile tables with columns ``case, percentile, e_rho .. e_k2``.

    ``case`` (``'A'``..``'F'``) selects one case; ``None`` returns all six.
    """
    df = _raw().rename(columns=THESIS_COLUMNS).copy()
    df["percentile"] = df["percentile"].astype(float)
    if case is not None:
        if case not in THESIS_TABLE_NUMBER:
            raise KeyError(f"no thesis table for case {case!r} (cases A-F)")
        df = df[df["case"] == case].reset_index(drop=True)
    return df
