"""Compare two percentile tables cell by cell (``spmc compare``, the CI golden check).

A table is a run directory's ``percentiles.csv`` (or ``.parquet``), or such a file
given directly. Cells are aligned on ``(filter, population, percentile)``; the compared
columns are the six errors and the ``trials`` / ``diverged`` counts. A cell is equal
when

    |a - b| <= atol + rtol * |b|      (b: the baseline)

with two infinities of the same sign equal, two NaNs equal, and a NaN against a number
a failure. A row or a column present in only one of the tables is a failure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from ..rundir.tables import ERROR_NAMES

KEY = ("filter", "population", "percentile")
VALUE_COLUMNS = (*ERROR_NAMES, "trials", "lost", "inconsistent", "diverged")
POPULATIONS = ("converged", "all", "both")


class CompareError(Exception):
    """A table that cannot be read or compared."""


def resolve_table_path(path: Path) -> Path:
    """A run directory -> its ``percentiles.csv`` (else ``percentiles.parquet``); a file -> itself."""
    from ..rundir.publish import dir_problems

    path = Path(path)
    bad = dir_problems(path if path.is_dir() else path.parent)  # an interrupted or mixed run's table
    if bad:
        raise CompareError(bad[0])
    if path.is_dir():
        for name in ("percentiles.csv", "percentiles.parquet"):
            if (path / name).is_file():
                return path / name
        raise CompareError(f"{path}: no percentiles.csv or percentiles.parquet in this directory")
    if not path.is_file():
        raise CompareError(f"{path}: no such file or directory")
    return path


def load_percentiles(path: Path) -> pd.DataFrame:
    """Read a percentile table; check its key columns and that each key appears once."""
    p = resolve_table_path(path)
    try:
        df = pd.read_parquet(p) if p.suffix == ".parquet" else pd.read_csv(p, comment="#")
    except Exception as exc:  # parse errors of several kinds
        raise CompareError(f"{p}: unreadable table ({type(exc).__name__}: {str(exc).splitlines()[0][:200]})") from None
    absent = [c for c in KEY if c not in df.columns]
    if absent:
        raise CompareError(f"{p}: not a percentile table (no column {', '.join(absent)})")
    df = df.copy()
    df["filter"] = df["filter"].astype(str)
    df["population"] = df["population"].astype(str)
    try:
        df["percentile"] = df["percentile"].astype(float)
    except ValueError:
        raise CompareError(f"{p}: column 'percentile' is not numeric") from None
    dup = df.duplicated(list(KEY))
    if dup.any():
        r = df[dup].iloc[0]
        raise CompareError(f"{p}: row ({r['filter']}, {r['population']}, {r['percentile']:g}) appears more than once")
    for c in VALUE_COLUMNS:
        if c in df.columns:
            try:
                df[c] = df[c].astype(float)
            except ValueError:
                raise CompareError(f"{p}: column {c!r} is not numeric") from None
    return df


def cell_equal(a: float, b: float, rtol: float, atol: float) -> bool:
    """``|a - b| <= atol + rtol |b|``; inf == inf (same sign), nan == nan, nan != number."""
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    if math.isinf(a) or math.isinf(b):
        return a == b
    return abs(a - b) <= atol + rtol * abs(b)


@dataclass(frozen=True)
class Cell:
    """One compared cell (or a whole missing row / column, with ``column`` '(row)' / '(column)')."""

    filter: str
    population: str
    percentile: float
    column: str
    run: float
    baseline: float
    ok: bool
    status: str

    @property
    def abs_diff(self) -> float:
        with_nan = math.isnan(self.run) or math.isnan(self.baseline)
        if with_nan or (math.isinf(self.run) and self.run == self.baseline):
            return math.nan
        return abs(self.run - self.baseline)

    @property
    def rel_diff(self) -> float:
        d = self.abs_diff
        return d / abs(self.baseline) if self.baseline not in (0.0,) and math.isfinite(d) else math.nan


@dataclass
class Comparison:
    """The result of :func:`compare_tables`."""

    run_name: str
    baseline_name: str
    rtol: float
    atol: float
    population: str
    cells: list[Cell] = field(default_factory=list)
    only_in_run: list[str] = field(default_factory=list)  # filters
    only_in_baseline: list[str] = field(default_factory=list)

    @property
    def failures(self) -> list[Cell]:
        return [c for c in self.cells if not c.ok]

    @property
    def ok(self) -> bool:
        return not self.failures and not self.only_in_run and not self.only_in_baseline


def compare_tables(
    run: pd.DataFrame,
    baseline: pd.DataFrame,
    rtol: float = 1e-6,
    atol: float = 0.0,
    population: str = "both",
    run_name: str = "RUN",
    baseline_name: str = "BASELINE",
) -> Comparison:
    """Align ``run`` and ``baseline`` on (filter, population, percentile) and compare every cell."""
    if population not in POPULATIONS:
        raise CompareError(f"population must be one of {', '.join(POPULATIONS)} (got {population!r})")
    if rtol < 0 or atol < 0:
        raise CompareError("rtol and atol must be >= 0")
    if population != "both":
        run = run[run["population"] == population]
        baseline = baseline[baseline["population"] == population]
    res = Comparison(run_name, baseline_name, rtol, atol, population)
    fr, fb = list(dict.fromkeys(run["filter"])), list(dict.fromkeys(baseline["filter"]))
    res.only_in_run = [f for f in fr if f not in fb]
    res.only_in_baseline = [f for f in fb if f not in fr]
    nan = math.nan
    for c in VALUE_COLUMNS:
        if (c in run.columns) != (c in baseline.columns):
            where = "run" if c not in run.columns else "baseline"
            res.cells.append(Cell("*", "*", nan, c, nan, nan, False, f"column missing in {where}"))
    cols = [c for c in VALUE_COLUMNS if c in run.columns and c in baseline.columns]
    a = run.set_index(list(KEY))
    b = baseline.set_index(list(KEY))
    keys = list(b.index) + [k for k in a.index if k not in b.index]
    for key in keys:
        f, pop, pct = key
        if key not in a.index:
            res.cells.append(Cell(f, pop, pct, "(row)", nan, nan, False, "row missing in run"))
            continue
        if key not in b.index:
            res.cells.append(Cell(f, pop, pct, "(row)", nan, nan, False, "row missing in baseline"))
            continue
        ra, rb = a.loc[key], b.loc[key]
        for c in cols:
            x, y = float(ra[c]), float(rb[c])
            ok = cell_equal(x, y, rtol, atol)
            status = "ok" if ok else ("nan mismatch" if math.isnan(x) != math.isnan(y) else "differs")
            res.cells.append(Cell(f, pop, pct, c, x, y, ok, status))
    return res


def compare_paths(
    run: Path, baseline: Path, rtol: float = 1e-6, atol: float = 0.0, population: str = "both"
) -> Comparison:
    """:func:`compare_tables` on two run directories or percentile files."""
    return compare_tables(load_percentiles(run), load_percentiles(baseline), rtol, atol, population,
                          str(run), str(baseline))  # fmt: skip


def _num(v: float) -> str:
    if math.isnan(v):
        return "nan"
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return f"{v:.10g}"


def format_comparison(res: Comparison, show_all: bool = False) -> str:
    """A Markdown report: a summary line, then a table of the out-of-tolerance cells (every cell with ``show_all``)."""
    n_fail = len(res.failures)
    out = [f"Comparing `{res.run_name}` (run) with `{res.baseline_name}` (baseline): "
           f"population {res.population}, |run - baseline| <= atol + rtol*|baseline| with "
           f"rtol={res.rtol:g}, atol={res.atol:g}.", ""]  # fmt: skip
    if res.only_in_baseline:
        out.append(f"- filters missing in run: {', '.join(res.only_in_baseline)}")
    if res.only_in_run:
        out.append(f"- filters missing in baseline: {', '.join(res.only_in_run)}")
    verdict = "FAIL" if not res.ok else "OK"
    out.append(f"**{verdict}**: {n_fail} of {len(res.cells)} cells out of tolerance.")
    shown = res.cells if show_all else res.failures
    if shown:
        out += ["", "| filter | population | pct | column | run | baseline | abs diff | rel diff | status |",
                "|---|---|---:|---|---:|---:|---:|---:|---|"]  # fmt: skip
        for c in shown:
            pct = "*" if math.isnan(c.percentile) else f"{c.percentile:g}"
            status = c.status if c.ok else f"**{c.status}**"
            nums = (c.run, c.baseline, c.abs_diff, c.rel_diff)
            vals = ["-"] * 4 if "missing" in c.status else [_num(v) for v in nums]
            out.append(f"| {c.filter} | {c.population} | {pct} | {c.column} | " + " | ".join(vals) + f" | {status} |")
    return "\n".join(out) + "\n"
