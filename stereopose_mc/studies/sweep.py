"""``spmc sweep``: a grid (or zipped list) of whole campaigns, one ordinary run directory per point.

``SCENARIO --set PATH=V1,V2,... [--set ...]`` sets the scenario value at ``PATH`` (a dotted
key path, with ``[i]`` for a list component: ``truth_initial_state.rho_m[1]``) to each
value in turn. The points are the Cartesian product of the ``--set`` lists (``--zip``:
the lists side by side, all of one length). Point ``i`` runs into ``DIR/pNNN-<values>``
with the scenario's root seed (so every point sees the same trial draws: a paired
comparison); ``DIR/sweep.json`` records the sweep. Rerunning the same command resumes:
finished points are skipped, unfinished ones resume their chunks. ``DIR/percentiles.csv``
stacks the points' percentile tables (filter labels ``<point>/<filter>``), so
``spmc compare`` works on two sweeps as on two runs.
"""

from __future__ import annotations

import itertools
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ContextManager

import pandas as pd
import yaml

from ..config.loader import ScenarioError, load_scenario_text, read_limited
from ..config.schema import Scenario
from ..mc import engine
from ..rundir import publish, store
from ..rundir.tables import ERROR_NAMES

SWEEP_FILE = "sweep.json"


class SweepError(Exception):
    """A sweep that cannot run as asked (bad --set, mismatched --zip lengths, another sweep in DIR)."""


@dataclass(frozen=True)
class Axis:
    path: str  # as given, e.g. truth_initial_state.rho_m[1]
    values: list[Any]


def _split_values(text: str) -> list[str]:
    """``1,2,[3,4]`` -> ``['1', '2', '[3,4]']`` (commas inside brackets kept)."""
    out, depth, cur = [], 0, ""
    for ch in text:
        if ch == "," and depth == 0:
            out.append(cur)
            cur = ""
            continue
        depth += ch in "[{"
        depth -= ch in "]}"
        cur += ch
    out.append(cur)
    return [v.strip() for v in out]


def is_key_path(path: str) -> bool:
    """``a.b.c`` or ``a.b[1]``: mapping keys joined by dots, each with optional ``[i]`` list indices."""
    return re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*(\[\d+\])*(\.[A-Za-z_][A-Za-z0-9_]*(\[\d+\])*)*", path) is not None


def set_strings(sets: dict[str, list[Any]]) -> list[str]:
    """``{PATH: [values]}`` -> the ``--set PATH=V1,V2,...`` strings (each value as JSON, which YAML reads back)."""
    return [f"{k}=" + ",".join(json.dumps(x) for x in v) for k, v in sets.items()]


def parse_set(text: str) -> Axis:
    """``PATH=V1,V2,...`` -> an :class:`Axis` (each value parsed as YAML)."""
    if "=" not in text:
        raise SweepError(f"--set {text!r}: expected PATH=V1,V2,...")
    path, vals = text.split("=", 1)
    path = path.strip()
    if not is_key_path(path):
        raise SweepError(f"--set {text!r}: {path!r} is not a key path (a.b.c, a.b[1])")
    parts = _split_values(vals)
    if not parts or any(p == "" for p in parts):
        raise SweepError(f"--set {text!r}: empty value")
    try:
        values = [yaml.safe_load(p) for p in parts]
    except yaml.YAMLError as exc:
        raise SweepError(f"--set {text!r}: unreadable value ({str(exc).splitlines()[0]})") from None
    return Axis(path, values)


def points_of(axes: list[Axis], zipped: bool) -> list[tuple[Any, ...]]:
    if zipped:
        lengths = {len(a.values) for a in axes}
        if len(lengths) > 1:
            raise SweepError("--zip needs every --set list to have the same length (got "
                             + ", ".join(f"{a.path}: {len(a.values)}" for a in axes) + ")")  # fmt: skip
        return list(zip(*(a.values for a in axes)))
    return list(itertools.product(*(a.values for a in axes)))


def set_path(d: dict, path: str, value: Any) -> None:
    """Set ``value`` at ``path`` in the raw scenario mapping ``d`` (creating absent or null mappings; lists must exist)."""
    tokens: list[Any] = []
    for part in path.split("."):
        m = re.fullmatch(r"([^\[]+)((?:\[\d+\])*)", part)
        tokens.append(m.group(1))
        tokens += [int(i) for i in re.findall(r"\[(\d+)\]", m.group(2))]
    cur: Any = d
    for i, tok in enumerate(tokens[:-1]):
        nxt = tokens[i + 1]
        if isinstance(tok, int):
            if not isinstance(cur, list) or tok >= len(cur):
                raise SweepError(f"--set {path}: index [{tok}] is out of range")
            cur = cur[tok]
        else:
            if not isinstance(cur, dict):
                raise SweepError(f"--set {path}: {tok!r} is not inside a mapping")
            if cur.get(tok) is None:  # absent, or null (an optional mapping left at its default)
                if isinstance(nxt, int):
                    raise SweepError(f"--set {path}: the scenario has no list {tok!r}")
                cur[tok] = {}
            cur = cur[tok]
    last = tokens[-1]
    if isinstance(last, int):
        if not isinstance(cur, list) or last >= len(cur):
            raise SweepError(f"--set {path}: index [{last}] is out of range")
    elif not isinstance(cur, dict):
        raise SweepError(f"--set {path}: not inside a mapping")
    cur[last] = value


def _fmt(v: Any) -> str:
    s = json.dumps(v, separators=(",", ""))
    return re.sub(r"[^A-Za-z0-9_.+-]+", "_", s).strip("_") or "_"


def point_name(i: int, axes: list[Axis], values: tuple[Any, ...]) -> str:
    short = "-".join(f"{_fmt(a.path.split('.')[-1])}={_fmt(v)}" for a, v in zip(axes, values))
    return f"p{i:03d}-{short}"[:120]


@dataclass
class Point:
    name: str
    values: dict[str, Any]
    scenario: Scenario


def build_points(scenario_file: Path, sets: list[str], zipped: bool, trials: int | None) -> tuple[list[Axis], list[Point]]:
    """Parse, expand and validate every point (all problems at once, as ``ScenarioError``)."""
    if not sets:
        raise SweepError("give at least one --set PATH=V1,V2,...")
    axes = [parse_set(s) for s in sets]
    if len({a.path for a in axes}) != len(axes):
        raise SweepError("each PATH may be swept by one --set only")
    try:
        text = read_limited(Path(scenario_file)).decode("utf-8")
    except OSError as exc:
        raise SweepError(f"{scenario_file}: cannot read ({exc.strerror or exc})") from None
    except ValueError as exc:  # too large, or not UTF-8
        raise SweepError(f"{scenario_file}: {exc}") from None
    load_scenario_text(text, str(scenario_file))  # the base scenario itself (file:line errors)
    base = yaml.safe_load(text)
    points, problems = [], []
    for i, vals in enumerate(points_of(axes, zipped)):
        d = json.loads(json.dumps(base))
        for a, v in zip(axes, vals):
            set_path(d, a.path, v)
        if trials is not None:
            d["trials"] = trials
        where = f"{scenario_file} with " + ", ".join(f"{a.path}={json.dumps(v)}" for a, v in zip(axes, vals))
        try:
            scn = load_scenario_text(yaml.safe_dump(d, sort_keys=False), where)
        except ScenarioError as exc:
            problems += exc.problems
            continue
        points.append(Point(point_name(i, axes, vals), {a.path: v for a, v in zip(axes, vals)}, scn))
    if problems:
        raise ScenarioError(problems)
    return axes, points


@dataclass
class SweepResult:
    out: Path
    points: list[Point]
    ran: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)


def _recorded_hash(run_dir: Path) -> str | None:
    """The scenario hash a point's run directory records (None: no readable run manifest)."""
    try:
        m = json.loads((run_dir / "manifest.json").read_bytes())
    except (OSError, ValueError):
        return None
    return m.get("scenario_hash") if isinstance(m, dict) and m.get("kind") == "run" else None


def _finished(run_dir: Path) -> bool:
    try:
        m = json.loads((run_dir / "manifest.json").read_bytes())
    except (OSError, ValueError):  # (ValueError: not JSON, or not UTF-8)
        return False
    return (isinstance(m, dict) and m.get("kind") == "run" and m.get("end") is not None
            and (run_dir / "trials.parquet").is_file() and not publish.problems(run_dir, m))  # fmt: skip


def run_sweep(scenario_file: Path, sets: list[str], out: Path, zipped: bool = False, trials: int | None = None,
              opts: engine.RunOptions | None = None, on_point: Callable[[int, int, Point, str], None] | None = None,
              progress_of: Callable[[Point], ContextManager] | None = None) -> SweepResult:  # fmt: skip
    """Run (or resume) every point of a sweep into ``out``; write ``sweep.json`` and ``percentiles.csv``."""
    axes, points = build_points(scenario_file, sets, zipped, trials)
    opts = opts or engine.RunOptions()
    out = Path(out)
    spec = {"kind": "sweep", "scenario": str(scenario_file), "sets": sets, "zip": zipped, "trials": trials,
            "axes": [{"path": a.path, "values": a.values} for a in axes],
            "points": [{"name": p.name, "values": p.values} for p in points]}  # fmt: skip
    sweep_file = out / SWEEP_FILE
    if sweep_file.is_file():
        try:
            old = json.loads(sweep_file.read_bytes())
        except (OSError, ValueError) as exc:
            raise SweepError(f"{sweep_file}: unreadable ({exc}); use another --out") from None
        if not isinstance(old, dict):
            raise SweepError(f"{sweep_file}: not a sweep file (not a JSON object); use another --out")
        if {k: old.get(k) for k in ("sets", "zip", "trials", "points")} != {k: spec[k] for k in ("sets", "zip", "trials", "points")}:
            raise SweepError(f"{out} holds a different sweep ({SWEEP_FILE}); use another --out")
        spec = old
    else:
        if out.exists() and any(out.iterdir()):
            raise SweepError(f"{out} already exists and is not a sweep directory")
        out.mkdir(parents=True, exist_ok=True)
        spec.update(store.base_manifest(opts.command), start=store.now_iso(), end=None)
        store.write_json(sweep_file, spec)
    res = SweepResult(out, points)
    for p in points:  # a point run before from another scenario (the scenario file changed): refused up front
        recorded = _recorded_hash(out / p.name)
        if recorded is not None and recorded != engine.scenario_hash(p.scenario):
            raise SweepError(f"{out / p.name}: ran from a different scenario (the scenario file or a --set value "
                             "changed since); use another --out")  # fmt: skip
    for i, p in enumerate(points):
        d = out / p.name
        if _finished(d):
            res.skipped.append(p.name)
            if on_point:
                on_point(i, len(points), p, "done")
            continue
        resume = (d / "manifest.json").is_file()
        o = engine.RunOptions(jobs=opts.jobs, chunk_size=opts.chunk_size, backend=opts.backend, kernels=opts.kernels,
                              scheduler=opts.scheduler, timeseries=opts.timeseries, resume=resume,
                              overwrite=not resume, command=opts.command)  # fmt: skip
        if on_point:
            on_point(i, len(points), p, "resume" if resume else "run")
        if progress_of is None:
            engine.run(p.scenario, d, o)
        else:
            with progress_of(p) as prog:
                engine.run(p.scenario, d, o, prog)
        res.ran.append(p.name)
    write_percentiles(out, points)
    spec["end"] = store.now_iso()
    store.write_json(sweep_file, spec)
    return res


def write_percentiles(out: Path, points: list[Point]) -> pd.DataFrame:
    """``DIR/percentiles.csv``: the points' percentile tables stacked, filter = ``<point>/<filter>``."""
    frames = []
    for p in points:
        pt = pd.read_csv(out / p.name / "percentiles.csv")
        pt["filter"] = p.name + "/" + pt["filter"].astype(str)
        frames.append(pt)
    df = pd.concat(frames, ignore_index=True)
    store.atomic_write_text(out / "percentiles.csv", df.to_csv(index=False, float_format="%.10g"))
    return df


def load_sweep(out: Path) -> dict:
    p = Path(out) / SWEEP_FILE
    try:
        spec = json.loads(p.read_bytes())
    except (OSError, ValueError) as exc:  # (ValueError: not JSON, or not UTF-8)
        raise SweepError(f"{out}: not a sweep directory ({exc})") from None
    if not isinstance(spec, dict) or spec.get("kind") != "sweep":
        raise SweepError(f"{out}: {SWEEP_FILE} is not a sweep")
    return spec


def summary(out: Path, quantiles: tuple[float, ...] = (10.0, 50.0, 90.0)) -> pd.DataFrame:
    """Per point and filter: the swept values, trials, divergence rate and quantiles of each metric (converged)."""
    import numpy as np

    spec = load_sweep(out)
    rows = []
    for p in spec["points"]:
        t = pd.read_parquet(Path(out) / p["name"] / "trials.parquet")
        for label, g in t.groupby("filter", sort=False):
            div = g["diverged"].to_numpy(bool)
            row = {"point": p["name"], **p["values"], "filter": label, "trials": len(g),
                   "diverged": int(div.sum()), "divergence_rate": float(div.mean())}  # fmt: skip
            for name in ERROR_NAMES:
                v = g.loc[~div, name].to_numpy(float)
                v = v[np.isfinite(v)]
                for q in quantiles:
                    row[f"{name}_p{q:g}"] = float(np.percentile(v, q, method="inverted_cdf")) if v.size else np.nan
            rows.append(row)
    return pd.DataFrame(rows)



def is_sweep_file(path: Path) -> bool:
    """A YAML file whose top level has a ``sweep`` mapping (rather than a scenario)."""
    try:
        d = yaml.safe_load(read_limited(Path(path)).decode("utf-8"))
    except (OSError, ValueError, yaml.YAMLError):  # ValueError: too large, or not UTF-8
        return False
    return isinstance(d, dict) and isinstance(d.get("sweep"), dict)


def load_sweep_file(path: Path) -> tuple[Path, list[str], bool, int | None]:
    """``sweep: {scenario, set: {PATH: [values]}, zip, trials}`` -> (scenario file, --set strings, zip, trials).

    ``scenario`` is relative to the sweep file.
    """
    path = Path(path)
    d = yaml.safe_load(read_limited(path).decode("utf-8"))["sweep"]
    unknown = sorted(set(d) - {"scenario", "set", "zip", "trials"})
    if unknown:
        raise SweepError(f"{path}: sweep.{unknown[0]}: unknown key (expected scenario, set, zip, trials)")
    if not isinstance(d.get("scenario"), str):
        raise SweepError(f"{path}: sweep.scenario: required, the scenario file (relative to this file)")
    sets = d.get("set")
    if not isinstance(sets, dict) or not sets:
        raise SweepError(f"{path}: sweep.set: required, a mapping of key paths to lists of values")
    for k, v in sets.items():
        if not isinstance(v, list) or not v:
            raise SweepError(f"{path}: sweep.set.{k}: must be a non-empty list of values")
    out = set_strings(sets)
    trials = d.get("trials")
    if trials is not None and (not isinstance(trials, int) or isinstance(trials, bool) or trials < 1):
        raise SweepError(f"{path}: sweep.trials: must be an integer >= 1")
    if not isinstance(d.get("zip", False), bool):
        raise SweepError(f"{path}: sweep.zip: must be true or false")
    return (path.parent / d["scenario"]), out, bool(d.get("zip", False)), trials
