"""Shared pieces of the benchmark suite: table rows, sizes, timing, scenario copies, output."""

from __future__ import annotations

import csv
import json
import math
import os
import statistics
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
CASE_B = ROOT / "configs" / "caseB.yaml"
SECTIONS = ("campaign", "chunk", "latency", "scaling", "memory", "baseline", "dispersed", "e2e", "realistic", "steps")
DEFAULT_SECTIONS = ("e2e", "realistic", "steps")  # what `make bench` runs: what users run, and the issue-36 targets
COLUMNS = ("section", "filter", "measure", "value", "unit", "target", "status", "note")


# ----------------------------------------------------------------------------- rows


@dataclass
class Row:
    """One line of the benchmark table.

    ``status`` is ``met`` / ``not met`` for a row with a target (suffix ``*`` when the
    number was measured at reduced size or projected from it; see ``note``), else ``""``.
    """

    section: str
    filter: str
    measure: str
    value: float
    unit: str
    target: str = ""
    status: str = ""
    note: str = ""


def judge(value: float, limit: float, kind: str, reduced: bool = False) -> str:
    """``met`` when ``value <= limit`` (``kind="max"``) or ``value >= limit`` (``"min"``)."""
    if not math.isfinite(value):
        ok = False
    elif kind == "max":
        ok = value <= limit
    elif kind == "min":
        ok = value >= limit
    else:
        raise ValueError(f"kind must be 'max' or 'min', not {kind!r}")
    return ("met" if ok else "not met") + ("*" if reduced else "")


# ----------------------------------------------------------------------------- sizes


@dataclass
class BenchConfig:
    """Sizes of every section. ``full()`` is what ``make bench`` runs; ``quick()`` the reduced one."""

    mode: str = "full"
    scenario: Path = CASE_B
    out: Path = ROOT / "runs" / "bench"
    filters: tuple[str, ...] = ("iekf", "ekf")  # filter types of the scenario to benchmark
    time_override: dict[str, float] | None = None  # replaces the scenario's `time` (tests)
    repeats: int = 3  # medians over this many repeats for measurements under `cheap_s`
    cheap_s: float = 2.0
    # campaign (spmc run in a subprocess)
    campaign_trials: int = 1000
    realistic_trials: int = 1000  # `realistic`: configs/mission-realistic.yaml, configs/mission-mesh-dispersed.yaml
    campaign_jobs: tuple[int, ...] = (1, 2)
    target_trials: int = 1000  # the size the campaign target is stated for
    # amortized cost per trial vs chunk size: {B: total trials}
    chunk_trials: dict[int, int] = field(default_factory=lambda: {1: 20, 10: 100, 100: 200, 1000: 1000})
    # single-trial step latency
    latency_steps: tuple[int, int] = (20, 100)
    latency_reps: int = 10
    latency_candidates: int = 10  # trials tried until one does not diverge
    # scaling with the number of feature points
    scaling_points: tuple[int, ...] = (5, 10, 20, 50)
    scaling_batch: int = 100
    growth_rounds: int = 7  # `steps`: interleaved rounds over N for the update growth (issue 14)
    scaling_steps: int = 5
    sphere_radius_m: float = 1.5
    feature_points: tuple[int, ...] = (5, 12, 24, 48)  # `steps` section: update cost per trial-step vs N
    cold_cache: bool = True  # `e2e`: empty Numba's cache before the cold compiled run
    memory_kernels: str = "compiled"  # `memory`: spmc run --kernels (threads with compiled)
    # peak memory (spmc run in a subprocess)
    memory_trials: int = 10000
    memory_jobs: int = 2
    memory_target_trials: int = 10000
    memory_interval_s: float = 0.1
    # FilterPy baseline
    baseline_trials: int = 20
    # `steps`: ours against FilterPy per computed step, run as the engine runs a chunk (the first
    # `baseline_trials` of them are FilterPy's trials)
    baseline_batch: int = 250
    baseline_rounds: int = 3  # `steps`: FilterPy's loop and the judged row, alternated (medians of each)
    keep_runs: bool = False
    blas_threads: int | None = None  # OPENBLAS/OMP/MKL_NUM_THREADS for the spmc subprocesses (None: as is)
    inproc_threads: int | None = 1  # BLAS threads of the in-process sections (the engine's chunks use 1)

    @classmethod
    def full(cls, **kw: Any) -> "BenchConfig":
        return cls(**kw)

    @classmethod
    def quick(cls, **kw: Any) -> "BenchConfig":
        base = dict(
            mode="quick", campaign_trials=100, realistic_trials=100, chunk_trials={1: 5, 10: 20, 100: 100},
            latency_reps=3,
            feature_points=(5, 12, 24),
            scaling_batch=20, scaling_steps=2, growth_rounds=3, memory_trials=1000, baseline_trials=20,
            baseline_batch=20, baseline_rounds=1,
        )  # fmt: skip
        base.update(kw)
        return cls(**base)

    def with_(self, **kw: Any) -> "BenchConfig":
        return replace(self, **kw)


# ----------------------------------------------------------------------------- timing


def log(msg: str) -> None:
    """Progress on stderr (stdout holds only the machine header and the table)."""
    print(f"[bench {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


@dataclass(frozen=True)
class Timing:
    median_s: float
    samples_s: tuple[float, ...]
    result: Any = None

    @property
    def n(self) -> int:
        return len(self.samples_s)


def timed(fn: Callable[[], Any], repeats: int = 3, cheap_s: float = 2.0) -> Timing:
    """Wall time of ``fn()``; repeated ``repeats`` times (median) when one call is under ``cheap_s``.

    Returns the result of the last call.
    """
    samples = []
    t0 = time.perf_counter()
    result = fn()
    samples.append(time.perf_counter() - t0)
    if samples[0] < cheap_s:
        for _ in range(repeats - 1):
            t0 = time.perf_counter()
            result = fn()
            samples.append(time.perf_counter() - t0)
    return Timing(statistics.median(samples), tuple(samples), result)


def fit_exponent(x: Iterable[float], y: Iterable[float]) -> float:
    """Slope ``p`` of the least-squares line ``log y = p log x + c`` (``y ~ x^p``)."""
    lx, ly = np.log(np.asarray(list(x), float)), np.log(np.asarray(list(y), float))
    A = np.stack([lx, np.ones_like(lx)], axis=1)
    coef, *_ = np.linalg.lstsq(A, ly, rcond=None)
    return float(coef[0])


def percentile(samples: Iterable[float], q: float) -> float:
    """The ``q``-th percentile that is an actual sample (numpy ``inverted_cdf``)."""
    return float(np.percentile(np.asarray(list(samples), float), q, method="inverted_cdf"))


# ----------------------------------------------------------------------------- scenarios


def scenario_dict(cfg: BenchConfig) -> dict:
    """The benchmark scenario as a YAML dict (with the configured ``time`` override)."""
    d = yaml.safe_load(Path(cfg.scenario).read_text())
    if cfg.time_override is not None:
        d["time"] = dict(cfg.time_override)
    return d


def single_filter(d: dict, kind: str) -> dict:
    """Copy of scenario dict ``d`` whose ``filters`` hold only its (first) filter of type ``kind``."""
    entries = [f for f in d.get("filters", []) if f.get("type") == kind]
    if not entries:
        raise ValueError(f"the scenario has no filter of type {kind!r} (filters: {d.get('filters')})")
    out = dict(d)
    out["filters"] = [dict(entries[0])]
    out["name"] = f"{d['name']}-{kind}"
    return out


def write_yaml(path: Path, d: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


def sphere_points(n: int, radius: float) -> np.ndarray:
    """``n`` points spread evenly over a sphere of ``radius`` (Fibonacci lattice), ``(n, 3)``."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    s = np.sqrt(1.0 - z * z)
    return radius * np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


@dataclass
class Prepared:
    """A scenario ready for in-process runs: what ``mc.engine`` computes once per process."""

    scenario: Any
    setup: Any
    truth: Any
    exact: Any
    filters: list  # FilterSetup, in scenario order
    bounds: Any

    def filter(self, kind: str):
        for fs in self.filters:
            if fs.kind == kind:
                return fs
        raise ValueError(f"no filter of type {kind!r}")

    def full_state_filter(self, kind: str):
        """The filter of type ``kind`` with ``error_state: full`` and the thesis's first-order pseudo-row ``R`` (the
        FilterPy baseline's full-state EKF)."""
        import dataclasses

        return dataclasses.replace(self.filter(kind), error_state="full", second_order=False)


def prepare(d: dict) -> Prepared:
    """Validate scenario dict ``d``; its setup, truth, exact measurements, filters and bounds.

    Built by the engine's own once-per-process preparation (``mc.engine.prepare``), so
    the in-process sections run exactly what ``spmc run`` runs.
    """
    from stereopose_mc.config.schema import Scenario
    from stereopose_mc.mc import engine

    scn, setup, truth, exact, filters, bounds = engine.prepare(Scenario.model_validate(d))
    return Prepared(scn, setup, truth, exact, list(filters), bounds)


def blas_limit(threads: int | None):
    """Context manager limiting BLAS threads (threadpoolctl), or a no-op when ``threads`` is None."""
    import contextlib

    if threads is None:
        return contextlib.nullcontext()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl is in the bench extra
        return contextlib.nullcontext()
    # the kernels' BLAS (SciPy's OpenBLAS, which Numba calls) loaded first: threadpoolctl limits the libraries loaded
    # when the limit is set, and the kernels load theirs lazily (a section that first loaded them inside the limit ran
    # their BLAS calls on 2 threads)
    import stereopose_mc.core.kernels  # noqa: F401

    return threadpool_limits(limits=threads)


# ----------------------------------------------------------------------------- output


def _fmt_value(v: float) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "nan"
    a = abs(v)
    if a == 0:
        return "0"
    if a >= 1e5 or a < 1e-3:
        return f"{v:.3g}"
    if a >= 100:
        return f"{v:.0f}"
    if a >= 10:
        return f"{v:.1f}"
    return f"{v:.3g}"


def format_table(rows: list[Row]) -> str:
    """The rows as one aligned plain-text (Markdown-compatible) table."""
    head = list(COLUMNS)
    body = [[r.section, r.filter, r.measure, _fmt_value(r.value), r.unit, r.target, r.status, r.note] for r in rows]
    widths = [max(len(h), *(len(b[i]) for b in body)) if body else len(h) for i, h in enumerate(head)]
    widths[-1] = len(head[-1])  # the note column is left ragged

    def line(cells):
        last = len(cells) - 1
        return "| " + " | ".join(c.ljust(w) if i < last else c for i, (c, w) in enumerate(zip(cells, widths))) + " |"

    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(head), sep] + [line(b) for b in body])


def write_outputs(rows: list[Row], meta: dict, out_dir: Path, stem: str) -> tuple[Path, Path]:
    """Write ``<stem>.csv`` (the table) and ``<stem>.json`` (table + machine + sizes) into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path, json_path = out_dir / f"{stem}.csv", out_dir / f"{stem}.json"
    with csv_path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(COLUMNS))
        w.writeheader()
        for r in rows:
            w.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in asdict(r).items()})
    payload = dict(meta)
    payload["rows"] = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in asdict(r).items()}
                       for r in rows]  # fmt: skip
    json_path.write_text(json.dumps(payload, indent=2, default=str) + "\n")
    return csv_path, json_path


# ----------------------------------------------------------------------------- shared by the sections


def spmc_command() -> list[str]:
    """``spmc`` next to the running interpreter (the venv's console script), else ``python -m``."""
    exe = Path(sys.executable).parent / "spmc"
    return [str(exe)] if exe.is_file() else [sys.executable, "-m", "stereopose_mc.cli.main"]


def subprocess_env(cfg: BenchConfig) -> dict[str, str]:
    env = dict(os.environ)
    if cfg.blas_threads:
        for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            env[k] = str(cfg.blas_threads)
    return env


def run_counts(run_dir: Path, steps: int) -> tuple[int, int, int]:
    """(diverged, rows, trial-steps computed) of a finished run directory; one row per trial and filter."""
    import pandas as pd

    t = pd.read_parquet(run_dir / "trials.parquet", columns=["diverged", "diverged_step"])
    return int(t["diverged"].sum()), len(t), active_trial_steps(t["diverged_step"].to_numpy(), steps)


def steps_of(d: dict) -> int:
    from stereopose_mc.config.schema import Scenario

    tm = Scenario.model_validate(d).time
    return int(round(tm.duration_s / tm.dt_s))


def engine_wall(run_dir: Path) -> float:
    m = json.loads((run_dir / "manifest.json").read_text())
    return float(m.get("wall_s_last_session", float("nan")))


def healthy(x: np.ndarray, P: np.ndarray, e: np.ndarray, bounds) -> bool:
    """The engine's divergence test for one trial: finite, P positive definite, errors in bounds."""
    if not (np.isfinite(x).all() and np.isfinite(P).all()):
        return False
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return False
    lim = np.array([bounds.rho_m, bounds.rho_dot_mps, bounds.omega_degps, np.inf, bounds.k, bounds.k])
    return not bool((e > lim).any())


def draws(prep: Prepared, trials: np.ndarray):
    """Noisy measurements and initial estimates of ``trials``, exactly as ``run_chunk`` draws them."""
    from stereopose_mc.sim import measurements as meas

    s = prep.setup
    draws = meas.draw_trials(prep.scenario.seed, trials, s.x0.size, s.steps, s.n_points)
    return meas.noisy(s, prep.exact, draws), meas.initial_estimates(s, draws)


def active_trial_steps(div_step: np.ndarray, K: int) -> int:
    """Trial-steps a run actually computed (a diverged trial stops after its divergence step)."""
    return int(np.where(div_step < 0, K, div_step).sum())


def single_trial_path(prep: Prepared, fs, trial: int):
    """Posteriors ``[(x, P)]_k`` and step measurements of one trial run with ``B = 1``; and health."""
    from stereopose_mc.filters import estimators, relnav
    from stereopose_mc.mc.trial import errors

    s, truth = prep.setup, prep.truth
    noisy, x0 = draws(prep, np.array([trial]))
    x, P = x0, estimators.initial_covariance(x0, np.diag(s.P0_diag)[None], fs)
    rows = np.arange(1)
    posts, steps, iters = [(x, P)], [None], []
    ok = True
    for k in range(1, s.steps + 1):
        vis = prep.exact.visible[k]
        step = relnav.StepMeasurement(y=relnav.stack_measurement(noisy.y[:, k], vis, s.pseudo), alpha=noisy.alpha[:, k],
                                      visible=vis, t=truth.t[k])  # fmt: skip
        with np.errstate(all="ignore"):
            xa, Pa = estimators.predict(x, P, truth.t[k - 1], fs, s)
            try:
                u = estimators.update(xa, Pa, step, rows, fs, s)
            except np.linalg.LinAlgError:
                return posts, steps, iters, False
        x, P = u.x, u.P
        posts.append((x, P))
        steps.append(step)
        iters.append(int(u.iterations[0]))
        ok = ok and healthy(x[0], P[0], errors(x[0], truth.x[k]), prep.bounds)
        if not ok:
            break
    return posts, steps, iters, ok


def step_latencies(sf, prep: Prepared, fs, posts, steps, k0: int, k1: int, reps: int) -> tuple[list, list]:
    """Wall times of ``sf.predict`` and ``sf.update`` (``B = 1``) from the recorded posteriors, steps ``k0..k1``."""
    one = np.arange(1)
    s = prep.setup

    def step_once(k: int) -> tuple[float, float]:
        x, P = posts[k - 1]
        t0 = time.perf_counter()
        xa, Pa = sf.predict(x, P, prep.truth.t[k - 1], fs, s)
        t1 = time.perf_counter()
        sf.update(xa, Pa, steps[k], one, fs, s)
        t2 = time.perf_counter()
        return t1 - t0, t2 - t1

    for k in range(k0, min(k0 + 5, k1) + 1):  # warm-up
        step_once(k)
    pred, upd = [], []
    for _ in range(reps):
        for k in range(k0, k1 + 1):
            a, b = step_once(k)
            pred.append(a)
            upd.append(b)
    return pred, upd


def scaling_scenario(cfg: BenchConfig, kind: str, n_points: int) -> dict:
    """Case copy with ``n_points`` points on a sphere, ``cfg.scaling_steps`` steps, one filter."""
    d = single_filter(scenario_dict(cfg), kind)
    d["target"] = dict(d["target"], feature_points_m=sphere_points(n_points, cfg.sphere_radius_m).tolist())
    dt = float(d.get("time", {}).get("dt_s", 1.0))
    d["time"] = {"dt_s": dt, "duration_s": cfg.scaling_steps * dt, "error_window_start_s": 0.0}
    return d


def first_healthy_path(prep: Prepared, fs, candidates: int):
    """``(trial, posteriors, steps, iterations)`` of the first of trials ``0..candidates-1`` that stays
    healthy with ``B = 1`` (:func:`single_trial_path`), or None when every one diverged."""
    for j in range(candidates):
        posts, stp, iters, ok = single_trial_path(prep, fs, j)
        if ok:
            return j, posts, stp, iters
    return None
