"""Self-contained HTML reports of run directories, and an index over several runs.

:func:`build_run_report` reads a run directory's tables (``config.yaml``,
``manifest.json``, ``trials.parquet`` and, when present, ``timeseries.parquet`` and
``timing.parquet``), regenerates the figures and tables into ``DIR/figures/`` without
re-running anything, and writes ``DIR/report.html``: one file with every image embedded
as a base64 PNG data URI, inline CSS, no JavaScript and no external reference, so it
opens offline and can be mailed or attached to a CI job as is.

:func:`build_index` writes ``index.html`` for a folder of runs: one row per run and
filter with the median and 90th percentile of each error, linking to each report.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd
import yaml

from ..rundir.publish import problems as publish_problems
from ..data import THESIS_COMPUTE_TIME_CASE_B_S, THESIS_TABLE_NUMBER, thesis_case, thesis_percentiles
from ..filters.registry import thesis_role
from ..rundir import store
from ..rundir.percentiles import percentile_table, reason_kind, wilson_interval
from ..rundir.tables import ERROR_LABELS, ERROR_NAMES
from . import faults_report, tracks_report
from . import figures as figs
from .html import cells as _cells, esc, figure_html, fmt_num, fmt_value, html_table, page
from . import sensitivity_report
from .summary import remedies, summarize

REQUIRED_FILES = ("config.yaml", "manifest.json", "trials.parquet")
OPTIONAL_TABLES = ("timeseries.parquet", "timing.parquet")
TRIALS_COLUMNS = ("trial", "filter", "diverged", *ERROR_NAMES)
DEFAULT_PERCENTILES = [50.0, 70.0, 90.0, 100.0]
THESIS_HEADERS = ["pct", "rho [m]", "rho_dot [m/s]", "omega [deg/s]", "theta [deg]", "k1", "k2"]


class ReportError(Exception):
    """A run directory a report cannot be built from; ``problems`` lists every reason."""

    def __init__(self, path: Path, problems: list[str]):
        self.path = Path(path)
        self.problems = list(problems)
        super().__init__(f"{path}: cannot build a report: " + "; ".join(self.problems))

    def lines(self) -> list[str]:
        """One line per problem, each naming the directory (for the CLI)."""
        return [f"{self.path}: {p}" for p in self.problems]


@dataclass
class RunData:
    """The tables of one run directory."""

    path: Path
    config: dict[str, Any]
    manifest: dict[str, Any]
    trials: pd.DataFrame
    timeseries: pd.DataFrame | None
    timing: pd.DataFrame | None
    notes: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return str(self.config.get("name") or self.manifest.get("scenario") or self.path.name)

    @property
    def filters(self) -> list[str]:
        """Labels of the filters in trials.parquet, in the run's order (manifest), then any others."""
        present = [str(f) for f in self.trials["filter"].unique()]
        listed = [str(f) for f in self.manifest.get("filters") or [] if str(f) in present]
        return list(dict.fromkeys(listed + present))

    @property
    def filter_types(self) -> dict[str, str]:
        """Filter label -> type (``ekf`` / ``iekf``) from config.yaml."""
        out = {}
        for f in self.config.get("filters") or []:
            if isinstance(f, dict) and f.get("type"):
                out[str(f.get("name") or f["type"])] = str(f["type"])
        return out

    @property
    def percentiles(self) -> list[float]:
        p = self.config.get("percentiles")
        return [float(x) for x in p] if isinstance(p, list) and p else DEFAULT_PERCENTILES

    @property
    def window_start(self) -> float | None:
        t = self.config.get("time") or {}
        v = t.get("error_window_start_s") if isinstance(t, dict) else None
        return float(v) if v is not None else None

    @property
    def state_dim(self) -> int | None:
        v = self.manifest.get("state_dim")
        return int(v) if v is not None else None

    @property
    def divergence(self) -> dict[str, Any]:
        d = self.config.get("divergence")
        return d if isinstance(d, dict) else {}

    @property
    def exclude_inconsistent(self) -> bool:
        return bool(self.divergence.get("exclude_inconsistent", False))

    def filter_config(self, label: str) -> dict[str, Any] | None:
        for f in self.config.get("filters") or []:
            if isinstance(f, dict) and str(f.get("name") or f.get("type")) == label:
                return f
        return None


# --------------------------------------------------------------------------- loading


def _read_parquet(path: Path, problems: list[str]) -> pd.DataFrame | None:
    try:
        return pd.read_parquet(path)
    except Exception as exc:  # pyarrow raises several types for damaged files
        problems.append(f"{path.name} is unreadable ({type(exc).__name__}: {str(exc).splitlines()[0][:200]})")
        return None


def load_run(run_dir: Path) -> RunData:
    """Read a run directory's tables; raise :class:`ReportError` listing everything missing or broken."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ReportError(run_dir, ["no such directory"])
    missing = [n for n in REQUIRED_FILES if not (run_dir / n).is_file()]
    problems = [f"missing {n}" for n in missing]
    config: dict = {}
    manifest: dict = {}
    trials = None
    if "config.yaml" not in missing:
        try:
            c = yaml.safe_load((run_dir / "config.yaml").read_text())
            if isinstance(c, dict):
                config = c
            else:
                problems.append("config.yaml is not a YAML mapping")
        except yaml.YAMLError as exc:
            problems.append(f"config.yaml is unreadable ({str(exc).splitlines()[0]})")
    if "manifest.json" not in missing:
        try:
            m = json.loads((run_dir / "manifest.json").read_text())
            if not isinstance(m, dict):
                problems.append("manifest.json is not a JSON object")
            elif m.get("kind") != "run":
                problems.append(f"manifest.json has kind {m.get('kind')!r}, not 'run' (not made by 'spmc run')")
            else:
                manifest = m
                unpublished = publish_problems(run_dir, m)
                if unpublished:  # what else is missing or odd follows from it
                    raise ReportError(run_dir, unpublished)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            problems.append(f"manifest.json is unreadable ({exc})")
    if "trials.parquet" not in missing:
        trials = _read_parquet(run_dir / "trials.parquet", problems)
        if trials is not None:
            absent = [c for c in TRIALS_COLUMNS if c not in trials.columns]
            if absent:
                problems.append(f"trials.parquet lacks columns {', '.join(absent)}")
            elif trials.empty:
                problems.append("trials.parquet has no rows")
    optional: dict[str, pd.DataFrame | None] = {}
    for name in OPTIONAL_TABLES:
        p = run_dir / name
        optional[name] = _read_parquet(p, problems) if p.is_file() else None
    if problems:
        raise ReportError(run_dir, problems)
    return RunData(run_dir, config, manifest, trials, optional["timeseries.parquet"], optional["timing.parquet"])


def is_run_dir(path: Path) -> bool:
    """A directory whose ``manifest.json`` says ``kind: run``."""
    m = _manifest(Path(path))
    return isinstance(m, dict) and m.get("kind") == "run"


UNREADABLE = object()  # _manifest: a manifest.json that is not UTF-8 JSON


def _manifest(path: Path) -> object:
    """The JSON value of ``path/manifest.json``; None if there is none (or it cannot be opened); ``UNREADABLE`` if
    it is not UTF-8 JSON."""
    try:
        return json.loads((path / "manifest.json").read_bytes())
    except OSError:
        return None
    except ValueError:  # json.JSONDecodeError, UnicodeDecodeError
        return UNREADABLE


def _looks_like_run(path: Path) -> bool:
    """A directory holding any run-directory file (possibly a broken run)."""
    return any((path / n).exists() for n in (*REQUIRED_FILES, *OPTIONAL_TABLES, "chunks", "percentiles.csv"))


def discover(path: Path) -> tuple[list[Path], bool]:
    """``([path], False)`` for a run directory, ``(runs, True)`` for a folder of runs.

    A folder is searched recursively for run directories (``manifest.json`` with kind
    ``run``, or one that cannot be read: its report lists the problem), without descending
    into them. Raises :class:`ReportError` for a path that is neither.
    """
    path = Path(path)
    if not path.is_dir():
        raise ReportError(path, ["no such directory"])
    if (path / "manifest.json").is_file() or _looks_like_run(path):
        return [path], False
    runs: list[Path] = []
    for root, dirs, _files in os.walk(path):
        dirs.sort()
        r = Path(root)
        if r != path and (is_run_dir(r) or _manifest(r) is UNREADABLE):
            runs.append(r)
            dirs.clear()
    if not runs:
        raise ReportError(path, ["not a run directory (no manifest.json) and no run directories below it"])
    return runs, True


# --------------------------------------------------------------------------- HTML helpers


# --------------------------------------------------------------------------- report sections

SUMMARY_SECTIONS = ("time", "leader", "target", "truth_initial_state", "camera", "measurements",
                    "initial_covariance", "divergence")  # fmt: skip


def _flatten(prefix: str, v: Any, out: list[tuple[str, str]]) -> None:
    if isinstance(v, dict):
        for k, x in v.items():
            _flatten(f"{prefix}.{k}" if prefix else str(k), x, out)
    elif prefix.endswith("feature_points_m") and isinstance(v, list):
        out.append((prefix, f"{len(v)} points: " + fmt_value(v)))
    else:
        out.append((prefix, fmt_value(v)))


def _kv(d: dict[str, Any]) -> str:
    return ", ".join(f"{k}={fmt_value(v)}" for k, v in d.items())


def scenario_rows(config: dict[str, Any]) -> list[tuple[str, str]]:
    """Key parameters of the resolved scenario as (key path, value) pairs."""
    rows = [(k, fmt_value(config.get(k))) for k in ("name", "description", "seed", "trials", "percentiles")]
    for sec in SUMMARY_SECTIONS:
        if sec in config:
            _flatten(sec, config[sec], rows)
    for f in config.get("filters") or []:
        if isinstance(f, dict):
            label = f.get("name") or f.get("type")
            keep = {k: v for k, v in f.items() if k not in ("name", "measurement_noise", "process_noise")}
            rows.append((f"filters.{label}", _kv(keep)))
            pn = f.get("process_noise")
            if isinstance(pn, dict):
                rows.append((f"filters.{label}.process_noise", _kv(pn)))
            mn = {k: v for k, v in (f.get("measurement_noise") or {}).items() if v is not None}
            if mn:
                rows.append((f"filters.{label}.measurement_noise", _kv(mn)))
    return rows


def run_fact_rows(data: RunData) -> list[tuple[str, str]]:
    """Facts from manifest.json and the tables: version, revision, seed, trials, timing."""
    m = data.manifest
    chunks = m.get("chunks") or []
    wall = sum(float(c.get("wall_s", 0.0)) for c in chunks if isinstance(c, dict))
    rows = [(k, fmt_value(m.get(k))) for k in ("version", "git_revision", "seed", "trials", "filters", "state_dim",
                                               "timeseries", "start", "end", "host", "scenario_hash")]  # fmt: skip
    rows.append(("chunks", f"{len(chunks)} (sum of chunk wall times {wall:.1f} s)"))
    if m.get("wall_s_last_session") is not None:
        rows.append(("wall_s_last_session", fmt_value(m.get("wall_s_last_session"))))
    cmd = m.get("command")
    if isinstance(cmd, list):
        rows.append(("command", " ".join(map(str, cmd))))
    rows.append(("trials.parquet rows", f"{len(data.trials)} ({data.trials['trial'].nunique()} trials)"))
    if data.timeseries is not None:
        rows.append(("timeseries.parquet", f"{data.timeseries['trial'].nunique()} trials, "
                                           f"{data.timeseries['step'].nunique()} steps"))  # fmt: skip
    return rows


def percentile_rows(pt: pd.DataFrame, label: str, population: str) -> list[list[str]]:
    g = pt[(pt["filter"] == label) & (pt["population"] == population)]
    return [[fmt_num(r["percentile"])] + _cells([r[n] for n in ERROR_NAMES]) for r in g.to_dict("records")]


def thesis_side(pt: pd.DataFrame, label: str, case: str) -> str:
    """Our converged table, the thesis's table and their ratio, side by side."""
    th = thesis_percentiles(case)
    ours = pt[(pt["filter"] == label) & (pt["population"] == "converged")].set_index("percentile")
    ratio_rows = []
    for r in th.to_dict("records"):
        p = r["percentile"]
        vals = [ours.at[p, n] / r[n] if p in ours.index and r[n] else np.nan for n in ERROR_NAMES]
        ratio_rows.append([fmt_num(p)] + _cells(vals))
    th_rows = [[fmt_num(r["percentile"])] + _cells([r[n] for n in ERROR_NAMES]) for r in th.to_dict("records")]
    ours_rows = percentile_rows(pt, label, "converged")
    return ('<div class="side">'
            + html_table(THESIS_HEADERS, ours_rows, caption=f"this run: {label}, converged")
            + html_table(THESIS_HEADERS, th_rows, caption=f"thesis Table {THESIS_TABLE_NUMBER[case]}: case {case}, "
                         "IEKF, 100 trials")
            + html_table(THESIS_HEADERS, ratio_rows, caption="ratio this run / thesis")
            + "</div>")  # fmt: skip


def reason_category(reason: str) -> str:
    """A lost or inconsistency reason without its numbers (``rundir.percentiles.reason_kind``)."""
    return reason_kind(reason)


def divergence_rows(data: RunData) -> list[list[str]]:
    """Per filter, flag (lost / inconsistent) and kind of reason: count, trials (first 10), median step and time."""
    t = data.config.get("time") or {}
    dt = float(t.get("dt_s", np.nan)) if isinstance(t, dict) else np.nan
    tr = data.trials
    flags = [("lost", "lost", "lost_reason", "lost_step")] if "lost" in tr else [
        ("lost", "diverged", "diverged_reason", "diverged_step")]
    if "inconsistent" in tr:
        flags.append(("inconsistent (flag)", "inconsistent", "inconsistent_reason", "inconsistent_step"))
    rows = []
    for label in data.filters:
        for what, flag, reason, step in flags:
            d = tr[(tr["filter"] == label) & tr[flag].astype(bool)]
            if d.empty:
                continue
            reasons = d[reason].astype(str) if reason in d else pd.Series("", index=d.index)
            d = d.assign(_cat=reasons.map(reason_category))
            for cat, g in sorted(d.groupby("_cat", sort=False), key=lambda kv: -len(kv[1])):
                ids = sorted(int(t) for t in g["trial"])
                shown = ", ".join(map(str, ids[:10])) + (f", ... ({len(ids) - 10} more)" if len(ids) > 10 else "")
                st = float(np.median(g[step])) if step in g else np.nan
                rows.append([esc(label), esc(what), esc(cat), str(len(ids)), esc(shown), esc(fmt_num(st)),
                             esc(fmt_num(st * dt))])  # fmt: skip
    return rows


def consistency_of(data: RunData) -> dict[str, Any]:
    """Per filter, its ``outputs.consistency.Consistency`` over the trials not lost (none for runs without the NEES
    block columns)."""
    from . import consistency

    t = data.config.get("time") or {}
    if not data.state_dim or "nees_gauge_mean" not in data.trials or not isinstance(t, dict):
        return {}
    try:
        dt, dur, w = float(t.get("dt_s", 1.0)), float(t.get("duration_s", 100.0)), float(t.get("error_window_start_s", 0))
    except (TypeError, ValueError):
        return {}
    steps = int(round((dur - w) / dt)) + 1
    return {label: consistency.summarize(data.trials, label, data.state_dim, steps) for label in data.filters}


def top_drivers(data: RunData, label: str, top: int = 3) -> str:
    """The ``top`` strongest significant drivers of the filter's errors (a dispersed run's ``sensitivity.csv``)."""
    path = data.path / "sensitivity.csv"
    if not data.config.get("dispersions") or not path.is_file():
        return ""
    tab = pd.read_csv(path)
    g = tab[(tab["filter"] == label) & (tab["statistic"] == "spearman") & tab["significant"].astype(bool)]
    if g.empty:
        return "no significant driver"
    g = g.reindex(g["value"].abs().sort_values(ascending=False, kind="stable").index).head(top)
    return "; ".join(f"{ERROR_LABELS.get(r.metric, r.metric)} \u2190 {r.parameter} (Spearman {r.value:+.2f}, "
                     f"n = {r.n})" for r in g.itertuples())  # fmt: skip


def diagnostics_rows(data: RunData) -> list[list[str]]:
    """Per filter: median NEES/NIS window means, mean IEKF iterations, trials with unconverged IEKF steps."""
    rows = []
    for label in data.filters:
        g = data.trials[data.trials["filter"] == label]
        col = lambda c: g[c].to_numpy(float) if c in g else np.array([np.nan])  # noqa: E731
        with np.errstate(all="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                vals = [np.nanmedian(col("nees_mean")), np.nanmedian(col("nis_mean")),
                        np.nanmean(col("iterations_mean"))]
        unconv = int(np.sum(col("iekf_unconverged_steps") > 0)) if "iekf_unconverged_steps" in g else "-"
        rows.append([esc(label)] + _cells(vals) + [esc(unconv)])
    return rows


def rate_cell(k: int, n: int) -> str:
    """A rate as a table cell: ``k / n`` and the percentage, then its 95 % Wilson interval."""
    if n <= 0:
        return "-"
    lo, hi = wilson_interval(k, n)
    return (f'<span class="ci0">{k} / {n} = <b>{100 * k / n:.0f} %</b></span><br>'
            f'<span class="ci">CI {100 * lo:.0f}-{100 * hi:.0f} %</span>')  # fmt: skip


def code_spans(text: str) -> str:
    """Markdown-style `code` spans of an escaped text as ``<code>`` elements."""
    return re.sub(r"`([^`]+)`", r"<code>\1</code>", text)


def results_summary_html(data: RunData) -> str:
    """The report's first screen: per filter, the lost and inconsistent rates with their 95 % Wilson intervals, the
    p50 / p90 of each per-trial mean error over the trials in the statistics (with their count), one consistency
    verdict naming the blocks that fail, the top drivers of a dispersed run, and what to try when most trials are
    lost (``outputs.summary``)."""
    excl = data.exclude_inconsistent
    sums = summarize(data.trials, data.filters, data.filter_types, excl)
    cons = consistency_of(data)
    pq = percentile_table(data.trials, [50, 90], excl)
    heads = ["filter", "type", "lost (95 % CI)", "inconsistent (95 % CI)", "trials in the statistics",
             *[f"{ERROR_LABELS[n]} p50 / p90" for n in ERROR_NAMES], "consistency"]  # fmt: skip
    rows, items, advice = [], [], []
    for s in sums:
        g = pq[(pq["filter"] == s.label) & (pq["population"] == "converged")].set_index("percentile")
        cells = [f"{fmt_num(g.at[50, n])} / {fmt_num(g.at[90, n])}" if len(g) else "-" for n in ERROR_NAMES]
        c = cons.get(s.label)
        ok = None if c is None or not c.trials else c.consistent
        word = {True: "consistent", False: "NOT consistent", None: "unknown"}[ok]
        cls = {True: "ok", False: "bad", None: "note"}[ok]
        rows.append([esc(s.label), esc(s.kind), rate_cell(s.lost, s.trials), rate_cell(s.inconsistent, s.trials),
                     str(s.kept), *[esc(v) for v in cells], f'<span class="{cls}">{esc(word)}</span>'])  # fmt: skip
        verdict = c.verdict().removeprefix(f"{s.label}, ") if c is not None and c.trials else word
        parts = [f'<span class="{cls}">{esc(verdict)}</span>']
        if s.lost_kinds:
            parts.append(f"<i>Lost</i>: {esc(s.kinds_words(s.lost_kinds))}.")
        if s.inconsistent_kinds:
            kinds = [(k.removeprefix("inconsistent: "), n) for k, n in s.inconsistent_kinds]
            parts.append(f"<i>Inconsistent</i> ({'left out' if excl else 'counted'}): {esc(s.kinds_words(kinds))}.")
        drivers = top_drivers(data, s.label)
        if drivers:
            parts.append(f"Top drivers: {esc(drivers)}.")
        items.append(f"<li><b>{esc(s.label)}</b>: " + " ".join(parts) + "</li>")
        advice += [f"<li>{code_spans(esc(r))}</li>" for r in remedies(s, data.filter_config(s.label))]
    window = f"t \u2265 {fmt_value(data.window_start)} s"
    pop = "the trials neither lost nor inconsistent" if excl else "the trials not lost (inconsistent ones count)"
    out = ["<h2>Results</h2>"]
    if excl:
        out.append('<p class="bad">This scenario sets <code>divergence.exclude_inconsistent: true</code>: trials '
                   "flagged inconsistent (a truth-based test) are left out of the accuracy statistics.</p>")  # fmt: skip
    out.append(html_table(heads, rows, left=2, caption=f"per-trial mean errors over {window}: 50th / 90th percentile "
                          f"over {pop}; rates with their 95 % Wilson interval"))  # fmt: skip
    out.append('<ul class="verdicts">' + "".join(items) + "</ul>")
    if advice:
        out.append('<h3>What went wrong, what to try</h3><ul class="advice">' + "".join(advice) + "</ul>")
    out.append('<p class="note"><b>Lost</b>: the filter\'s own tests stopped it (NIS window, gate lock-out, '
               "non-finite or not positive definite covariance, linear-algebra failure). <b>Inconsistent</b>: a "
               "truth-based test (error bounds, NEES far beyond the claimed covariance) flagged it; the filter ran on "
               "and its errors count. Consistency: median over the trials not lost of the time-averaged NEES per "
               "degree of freedom (full n - 1, gauge-projected n - 4, per block; at most 2) and of the NIS per "
               "measurement dimension (inside its 95 % band); docs/outputs.md.</p>")  # fmt: skip
    return "".join(out)


def render_report(data: RunData, fs: figs.FigureSet, extra: list[str] | None = None) -> str:
    """The report's HTML text; ``extra``: HTML blocks placed before the figures (the sensitivity section)."""
    pt = percentile_table(data.trials, data.percentiles, data.exclude_inconsistent)
    case = thesis_case(data.name)
    types = data.filter_types
    window = data.window_start
    body = [f"<h1>{esc(data.name)}: Monte Carlo report</h1>"]
    if data.config.get("description"):
        body.append(f"<p>{esc(data.config['description'])}</p>")
    body.append(f"<p class=\"note\">Run directory <code>{esc(data.path)}</code>. Errors are per-trial means over "
                f"t &ge; {esc(fmt_value(window))} s; units: rho m, rho_dot m/s, omega deg/s, theta deg, k1 and k2 "
                "dimensionless.</p>")  # fmt: skip

    body.append(results_summary_html(data))
    body.append("<h2>Percentile tables</h2>")
    for label in data.filters:
        g = pt[pt["filter"] == label]
        if g.empty:
            continue
        n = int(g["trials"].iloc[0])
        kept = int(g.loc[g["population"] == "converged", "trials"].iloc[0])
        nl = int(g["lost"].iloc[0]) if "lost" in g else int(g["diverged"].iloc[0])
        ni = int(g["inconsistent"].iloc[0]) if "inconsistent" in g else 0
        kind = types.get(label, "?")
        body.append(f"<h3>{esc(label)} ({esc(kind)}): {kept} of {n} trials in the statistics; {nl} lost, "
                    f"{ni} inconsistent</h3>")  # fmt: skip
        cap = f"trials not lost ({kept})" + (", nor inconsistent" if data.exclude_inconsistent else "")
        if case is not None and thesis_role(kind) == "iekf":
            body.append(thesis_side(pt, label, case))
        else:
            body.append(html_table(THESIS_HEADERS, percentile_rows(pt, label, "converged"), caption=cap))
        if kept < n:
            body.append(html_table(THESIS_HEADERS, percentile_rows(pt, label, "all"),
                                   caption=f"all {n} trials (a lost trial counts as +inf)"))  # fmt: skip
    if case is not None and not any(thesis_role(types.get(f)) == "iekf" for f in data.filters):
        th = thesis_percentiles(case)
        rows = [[fmt_num(r["percentile"])] + _cells([r[n] for n in ERROR_NAMES]) for r in th.to_dict("records")]
        cap = f"thesis Table {THESIS_TABLE_NUMBER[case]}: case {case}, IEKF, 100 trials"
        body.append(html_table(THESIS_HEADERS, rows, caption=cap))

    body.append("<h2>Lost and inconsistent trials</h2>")
    drows = divergence_rows(data)
    if drows:
        heads = ["filter", "flag", "kind of reason", "trials", "trial ids", "median step", "median t [s]"]
        body.append(html_table(heads, drows, left=3))
    else:
        body.append("<p>No trial was lost or flagged inconsistent.</p>")

    body.append("<h2>Filter diagnostics</h2>")
    body.append(html_table(["filter", "median NEES (window mean)", "median NIS (window mean)",
                            "mean IEKF iterations per step", "trials with unconverged IEKF steps"],
                           diagnostics_rows(data)))  # fmt: skip
    body += faults_report.section(data)
    body += tracks_report.section(data)

    body.append("<h2>Compute time per trial</h2>")
    if data.timing is not None and not data.timing.empty:
        ct = figs.compute_time_table(data.timing)
        rows = [[esc(r["filter"]), str(r["trials"])] + _cells([r["max_s"], r["mean_s"], r["min_s"]])
                for r in ct.to_dict("records")]  # fmt: skip
        if case == "B":
            t = THESIS_COMPUTE_TIME_CASE_B_S
            rows.append(["thesis Table 6.7 (IEKF, MATLAB, Xeon E5-2609)", "200"]
                        + _cells([t["max"], t["mean"], t["min"]]))
        body.append(html_table(["filter", "trials", "max [s]", "mean [s]", "min [s]"], rows))
    else:
        body.append("<p>No timing.parquet in this run.</p>")

    body += extra or []
    body.append("<h2>Figures</h2>")
    for f in fs.figures:
        body.append(figure_html(f, data.path))
    notes = data.notes + fs.notes
    if notes:
        body.append("<h2>Notes</h2><ul>" + "".join(f"<li>{esc(n)}</li>" for n in notes) + "</ul>")

    body.append("<h2>Scenario and run</h2>")
    body.append("<details><summary>Resolved scenario (config.yaml)</summary>"
                + html_table(["key", "value"], [[esc(k), esc(v)] for k, v in scenario_rows(data.config)], left=2)
                + "</details>")  # fmt: skip
    body.append("<details><summary>Run facts (manifest.json)</summary>"
                + html_table(["key", "value"], [[esc(k), esc(v)] for k, v in run_fact_rows(data)], left=2)
                + "</details>")  # fmt: skip
    return page(f"{data.name}: Monte Carlo report", body)


def build_run_report(run_dir: Path, progress: Callable[[str], None] | None = None, jobs: int = 1) -> Path:
    """Regenerate ``DIR/figures/`` from the run's tables and write ``DIR/report.html``; return its path.

    ``jobs``: processes drawing the figures (``figures.draw_all``; the same files for any ``jobs``).

    Raises :class:`ReportError` (listing every missing or unreadable file) for a broken
    or partial run directory; nothing is written then. The figures are drawn into a hidden
    staging directory and swapped in whole, so an interrupted report leaves the previous
    ``figures/`` as it was.
    """
    data = load_run(Path(run_dir))
    final = data.path / "figures"
    stage = data.path / f".figures-staging-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    try:
        fs, todo = figs.plan_figures(stage, data.trials, data.timeseries, data.timing,
                                     filters=data.filters, filter_types=data.filter_types, state_dim=data.state_dim,
                                     window_start=data.window_start, percentiles=data.percentiles)  # fmt: skip
        sens_html, sens_todo = sensitivity_report.section(data.path, data.trials, data.config, data.filters)
        fs.figures += figs.drawn_files(todo + sens_todo, stage, jobs, progress)  # (one batch: every process busy)
        _swap_in(stage, final)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    fs.figures = [dataclasses.replace(f, png=final / Path(f.png).name, svg=final / Path(f.svg).name)
                  for f in fs.figures]  # fmt: skip
    fs.tables = [final / Path(t).name for t in fs.tables]
    out = data.path / "report.html"
    store.atomic_write_text(out, render_report(data, fs, sens_html))
    return out


def _swap_in(stage: Path, final: Path) -> None:
    """Replace directory ``final`` by ``stage`` (two renames; the old one is removed afterwards)."""
    old = final.with_name(f".figures-old-{os.getpid()}")
    shutil.rmtree(old, ignore_errors=True)
    if final.exists():
        os.replace(final, old)
    os.replace(stage, final)
    shutil.rmtree(old, ignore_errors=True)


# --------------------------------------------------------------------------- index of several runs

INDEX_PERCENTILES = (50.0, 90.0)


def index_rows(data: RunData, link: str, shown: str) -> list[list[str]]:
    """One row per filter: run link, filter, trials, diverged, median and p90 of each error (converged)."""
    pt = percentile_table(data.trials, list(INDEX_PERCENTILES))
    rows = []
    for label in data.filters:
        g = pt[(pt["filter"] == label) & (pt["population"] == "converged")].set_index("percentile")
        if g.empty:
            continue
        n, nd = int(g["trials"].iloc[0]) + int(g["diverged"].iloc[0]), int(g["diverged"].iloc[0])
        cells = [f'<a href="{esc(link)}">{esc(shown)}</a>', esc(data.name), esc(label), str(n), str(nd)]
        for name in ERROR_NAMES:
            cells += _cells([g.at[p, name] for p in INDEX_PERCENTILES])
        rows.append(cells)
    return rows


def build_index(folder: Path, runs: list[Path], failed: dict[Path, list[str]] | None = None) -> Path:
    """Write ``folder/index.html`` comparing ``runs`` side by side; list ``failed`` runs with their problems."""
    folder = Path(folder)
    headers = ["run", "scenario", "filter", "trials", "diverged"]
    for name in ERROR_NAMES:
        headers += [f"{ERROR_LABELS[name]} p50", f"{ERROR_LABELS[name]} p90"]
    rows = []
    for r in runs:
        data = load_run(r)
        rel = os.path.relpath(r, folder).replace(os.sep, "/")
        rows += index_rows(data, f"{rel}/report.html", rel)
    body = [f"<h1>Monte Carlo runs in {esc(folder.name or folder)}</h1>",
            "<p class=\"note\">Median (p50) and 90th percentile (p90) of the per-trial mean errors over the "
            "converged trials of each run and filter; units m, m/s, deg/s, deg, -, -. The run name links to its "
            "report.</p>", html_table(headers, rows, left=3)]  # fmt: skip
    if failed:
        body.append("<h2>Runs without a report</h2><ul>")
        body += [f"<li><code>{esc(os.path.relpath(p, folder))}</code>: {esc('; '.join(pr))}</li>"
                 for p, pr in failed.items()]
        body.append("</ul>")
    out = folder / "index.html"
    store.atomic_write_text(out, page(f"Monte Carlo runs in {folder.name}", body))
    return out
