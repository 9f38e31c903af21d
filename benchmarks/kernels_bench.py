"""Sections of issue 14: numpy vs compiled kernels side by side, with ratios.

- ``e2e``: the case-B campaign as configured (both filters), ``--jobs 2``, end to end in a
  subprocess, per kernels: cold (compiled: Numba's on-disk cache emptied first, i.e. the
  first run after install) and warm; start-up (``spmc --help``; a 2-trial run, warm).
- ``steps``: per-step latency at B = 1 (predict + update, after convergence);
  throughput (trial-steps/s of ``run_filter`` in-process) at B = 1, 10, 100, 1000; the
  update's cost against the number of feature points (5, 10, 20, 40, fitted exponent);
  the FilterPy EKF loop per computed step against our compiled EKF.

Every time is a wall-clock median; ``ratio`` rows are numpy / compiled.
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .common import (
    active_trial_steps,
    BenchConfig,
    blas_limit,
    CASE_B,
    draws,
    engine_wall,
    first_healthy_path,
    fit_exponent,
    judge,
    log,
    prepare,
    Row,
    run_counts,
    scaling_scenario,
    scenario_dict,
    spmc_command,
    step_latencies,
    steps_of,
    subprocess_env,
    timed,
    write_yaml,
)

KERNELS = ("numpy", "compiled")
TARGET_E2E_S = 5.0  # case B, 1,000 trials, the default command, warm
TARGET_FIRST_RUN_S = 15.0  # the same, the first run after an install (make venv)
TARGET_UPDATE_EXPONENT = 1.5  # update cost per trial-step ~ N^p, N = 5 ... 48


def _spmc(args: list[str], env=None) -> tuple[float, subprocess.CompletedProcess]:
    t0 = time.perf_counter()
    r = subprocess.run(spmc_command() + args, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(f"spmc {' '.join(args)} failed ({r.returncode}): {r.stderr.strip()[-2000:]}")
    return wall, r


def numba_cache_dirs() -> list[Path]:
    """Where Numba keeps the compiled kernels of ``core/kernels`` (``cache=True``: ``__pycache__`` beside them)."""
    import stereopose_mc.core.kernels as k

    return [Path(k.__file__).parent / "__pycache__"]


def clear_numba_cache() -> int:
    n = 0
    for d in numba_cache_dirs():
        for p in list(d.glob("*.nbi")) + list(d.glob("*.nbc")):
            p.unlink()
            n += 1
    return n


def ensure_bytecode() -> str:
    """Write the package's Python bytecode (``__pycache__``) where it is missing or stale; a note for the rows.

    A first run writes it on any machine that allows it. Where ``PYTHONDONTWRITEBYTECODE`` is set
    (this benchmark's sandbox sets it), an editable install never gets it and every ``spmc``
    process compiles the package's ~80 modules from source again (~0.08 s of a two-trial run, measured),
    which a warm start on an ordinary machine does not pay. ``make venv`` compiles it too.
    """
    import compileall

    import stereopose_mc

    compileall.compile_dir(Path(stereopose_mc.__file__).parent, quiet=1)
    off = bool(os.environ.get("PYTHONDONTWRITEBYTECODE"))
    return "package bytecode precompiled (PYTHONDONTWRITEBYTECODE is set here)" if off else "package bytecode cached"


def _default_run(scenario: Path, out: Path, trials: int, *extra: str) -> list[str]:
    """The command a user types (no performance flag), made quiet and without the report."""
    return ["run", str(scenario), "--trials", str(trials), "--out", str(out), "--overwrite", "--quiet", "--no-report",
            *extra]  # fmt: skip


def _warm_step(env) -> float:
    """Wall of ``make venv``'s warm step (``python -m stereopose_mc.mc.warm``) in a subprocess."""
    import sys

    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "stereopose_mc.mc.warm"], capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise RuntimeError(f"the warm step failed ({r.returncode}): {r.stderr.strip()[-2000:]}")
    return time.perf_counter() - t0


def e2e(cfg: BenchConfig, tmp: Path, ctx: dict[str, Any]) -> list[Row]:
    """The default command (``spmc run SCENARIO --trials T``, no flag) end to end: cold after an install (Numba's
    cache and the truth cache emptied, then ``make venv``'s warm step, then the run), warm, the numpy reference;
    start-up."""

    bytecode = ensure_bytecode()
    log(f"e2e: {bytecode}")
    rows: list[Row] = []
    d = scenario_dict(cfg)
    scn = write_yaml(tmp / "e2e.yaml", d)
    T = cfg.campaign_trials
    env = subprocess_env(cfg)
    truth_cache = tmp / "spmc-cache"  # a truth cache of this benchmark (sim/truth_cache.py), emptied for cold runs
    env["SPMC_CACHE_DIR"] = str(truth_cache)
    reduced = T != cfg.target_trials
    out = tmp / "e2e-run"

    def row(measure: str, wall: float, target_s: float | None = None, note: str = "") -> Row:
        tgt = st = ""
        if target_s is not None:
            proj = wall * cfg.target_trials / T
            tgt, st = f"<= {target_s:g} s ({cfg.target_trials:,} trials)", judge(proj, target_s, "max", reduced)
            if reduced:
                note = f"*projected {proj:.1f} s for {cfg.target_trials:,} trials (linear); " + note
        return Row("e2e", "iekf+ekf", measure, wall, "s", tgt, st, note)

    def counts() -> str:
        ndiv, ntr, _ = run_counts(out, steps_of(d))
        return f"engine {engine_wall(out):.2f} s; {ndiv}/{ntr} (trial, filter) runs diverged"

    if cfg.cold_cache:
        shutil.rmtree(truth_cache, ignore_errors=True)
        log(f"e2e: cleared {clear_numba_cache()} Numba cache files; the install's warm step")
        w = _warm_step(env)
        rows.append(Row("e2e", "-", "install: make venv's warm step (python -m stereopose_mc.mc.warm), cold", w, "s",
                        note="compiles every kernel signature into Numba's cache (a few steps of 3 scenarios)"))
        log(f"e2e: first run after the install, {T} trials")
        w, _ = _spmc(_default_run(scn, out, T), env)
        rows.append(row(f"first run after install, {T:,} trials, default command", w, TARGET_FIRST_RUN_S,
                        counts() + f"; {bytecode}"))  # fmt: skip
    walls, engines, own = [], [], []
    pinned = env.get("OPENBLAS_CORETYPE")  # an environment that chooses OpenBLAS's kernels (this one: Haswell)
    own_env = {k: v for k, v in env.items() if k != "OPENBLAS_CORETYPE"}
    for _ in range(max(1, cfg.repeats)):  # this shared machine's speed drifts by 10-15 % between minutes: a median
        log(f"e2e: warm, {T} trials, default command")
        walls.append(_spmc(_default_run(scn, out, T), env)[0])
        engines.append(engine_wall(out))
        if pinned:  # alternated with the judged runs: the same minutes of this machine
            log(f"e2e: warm, {T} trials, default command, OpenBLAS's own kernels (OPENBLAS_CORETYPE unset)")
            own.append(_spmc(_default_run(scn, tmp / "e2e-own", T), own_env)[0])  # (not `out`: the judged counts)
    warm = float(np.median(walls))
    rows.append(row(f"wall, {T:,} trials, default command, warm", warm, TARGET_E2E_S,
                    f"median of {len(walls)} ({', '.join(f'{w:.2f}' for w in walls)} s); " + counts()))  # fmt: skip
    shutil.rmtree(tmp / "e2e-own", ignore_errors=True)
    if own:
        rows.append(row(f"wall, {T:,} trials, default command, warm, OpenBLAS's own kernels", float(np.median(own)),
                        None, f"OPENBLAS_CORETYPE={pinned} of this environment unset; median of {len(own)} "
                        f"({', '.join(f'{w:.2f}' for w in own)} s), alternated with the judged row's runs"))  # fmt: skip
    log("e2e: make demo's command (the README's: spmc run configs/caseB.yaml, with its report)")
    demo = tmp / "e2e-demo"
    own_trials = int(yaml.safe_load(CASE_B.read_text())["trials"])  # what `make demo` runs
    n_demo = min(T, own_trials)  # (at full size the command itself; fewer trials when reduced)
    less = [] if n_demo == own_trials else ["--trials", str(n_demo)]
    w_demo, _ = _spmc(["run", str(CASE_B), "--out", str(demo), "--overwrite", "--quiet", *less], env)
    w_rep, _ = _spmc(["report", str(demo), "--quiet"], env)
    rows.append(Row("e2e", "iekf+ekf", f"make demo's command (spmc run configs/caseB.yaml: {n_demo} trials and the "
                    "report), warm", w_demo, "s", note=f"the report alone (spmc report of that run, after it): "
                    f"{w_rep:.1f} s (its figures drawn on every core)"))  # fmt: skip
    shutil.rmtree(demo, ignore_errors=True)
    log(f"e2e: numpy reference, {T} trials")
    w_np, _ = _spmc(_default_run(scn, out, T, "--kernels", "numpy"), env)
    rows.append(row(f"wall, {T:,} trials, --kernels numpy (the reference), warm", w_np, None, counts()))
    rows.append(Row("e2e", "iekf+ekf", "ratio numpy / compiled (warm, default jobs)", w_np / warm, "x"))
    shutil.rmtree(out, ignore_errors=True)
    helps = [_spmc(["--help"], env)[0] for _ in range(max(3, cfg.repeats))]
    rows.append(Row("e2e", "-", "spmc --help, warm: median", float(np.median(helps)), "s",
                    note=f"median of {len(helps)}"))  # fmt: skip
    two = tmp / "e2e-two"
    _spmc(_default_run(scn, two, 2), env)
    walls = [_spmc(_default_run(scn, two, 2), env)[0] for _ in range(max(3, cfg.repeats))]
    rows.append(Row("e2e", "iekf+ekf", "2-trial run, warm, default command: median", float(np.median(walls)), "s",
                    note=f"median of {len(walls)}; interpreter, imports, truth (cached), 2 trials, Parquet; "
                         f"{bytecode}"))  # fmt: skip
    shutil.rmtree(two, ignore_errors=True)
    return rows


REALISTIC = (("mission-realistic.yaml", 30.0), ("mission-mesh-dispersed.yaml", 60.0))


def realistic(cfg: BenchConfig, tmp: Path, ctx: dict[str, Any]) -> list[Row]:
    """The default command on the realistic scenarios (configs/), every filter of each, warm."""
    from .common import ROOT

    rows: list[Row] = []
    env = subprocess_env(cfg)
    T = cfg.realistic_trials
    reduced = T != cfg.target_trials
    for name, target_s in REALISTIC:
        scn = ROOT / "configs" / name
        out = tmp / f"realistic-{scn.stem}"
        d = scenario_dict(cfg.with_(scenario=scn))
        if cfg.time_override is not None:  # (tests) a short copy, its mesh file named by its absolute path
            shape = d["target"].get("shape") or {}
            if shape.get("type") == "mesh":
                d["target"]["shape"] = dict(shape, file=str((scn.parent / shape["file"]).resolve()))
            scn = write_yaml(tmp / name, d)
        _spmc(_default_run(scn, tmp / "realistic-warm-up", 2), env)  # Numba's cache: the run's, not the compiler's
        log(f"realistic: {name}, {T} trials, default command")
        w, _ = _spmc(_default_run(scn, out, T), env)

        ndiv, ntr, tsteps = run_counts(out, steps_of(d))
        proj = w * cfg.target_trials / T
        note = (f"{'*projected %.0f s for %s trials (linear); ' % (proj, f'{cfg.target_trials:,}') if reduced else ''}"
                f"engine {engine_wall(out):.1f} s; {ndiv}/{ntr} (trial, filter) runs diverged; "
                f"{1e3 * w / T:.0f} ms per trial")  # fmt: skip
        filters = "+".join(f.get("name") or f["type"] for f in d["filters"])
        rows.append(Row("realistic", filters, f"{scn.stem}: wall, {T:,} trials, default command", w, "s",
                        f"<= {target_s:g} s ({cfg.target_trials:,} trials)", judge(proj, target_s, "max", reduced),
                        note))  # fmt: skip
        shutil.rmtree(out, ignore_errors=True)
        shutil.rmtree(tmp / "realistic-warm-up", ignore_errors=True)
    return rows


def _run_filter(prep, fs, trials, kernels):
    from stereopose_mc.mc.trial import run_filter

    noisy, x0 = draws(prep, trials)
    s = prep.setup

    def go():
        with np.errstate(all="ignore"):
            return run_filter(x0, s, prep.truth, noisy.y, noisy.alpha, prep.exact.visible, fs, prep.bounds,
                              kernels=kernels)  # fmt: skip

    return go


def steps(cfg: BenchConfig, tmp: Path, ctx: dict[str, Any]) -> list[Row]:
    """Latency at B = 1, throughput vs B, update cost vs N, FilterPy per computed step; numpy vs compiled."""
    with blas_limit(cfg.inproc_threads):
        return _latency(cfg) + _throughput(cfg) + _features(cfg) + _filterpy(cfg)


def _latency(cfg: BenchConfig) -> list[Row]:
    from stereopose_mc.mc.trial import step_functions

    rows: list[Row] = []
    prep = prepare(scenario_dict(cfg))
    s = prep.setup
    K = s.steps
    k0, k1 = max(1, min(cfg.latency_steps[0], K)), min(cfg.latency_steps[1], K)
    for kind in cfg.filters:
        fs = prep.filter(kind)
        path = first_healthy_path(prep, fs, cfg.latency_candidates)
        if path is None:
            continue
        j, posts, stp, iters = path
        med = {}
        for kernels in KERNELS:
            pred, upd = step_latencies(step_functions(kernels), prep, fs, posts, stp, k0, k1, cfg.latency_reps)
            tot = np.add(pred, upd)
            med[kernels] = 1e3 * float(np.median(tot))
            rows.append(Row("steps", kind, f"latency B=1, step predict+update, {kernels}: median", med[kernels], "ms",
                            note=f"trial {j}, steps {k0}-{k1}, {tot.size} samples; predict "
                            f"{1e3 * np.median(pred):.3g} ms, update {1e3 * np.median(upd):.3g} ms; "
                            f"mean iterations {np.mean(iters[k0 - 1:k1]):.2f}"))  # fmt: skip
        rows.append(Row("steps", kind, "latency B=1: ratio numpy / compiled", med["numpy"] / med["compiled"], "x"))
    return rows


def _throughput(cfg: BenchConfig) -> list[Row]:
    rows: list[Row] = []
    prep = prepare(scenario_dict(cfg))
    K = prep.setup.steps
    for kind in cfg.filters:
        fs = prep.filter(kind)
        for B in sorted(cfg.chunk_trials):
            rate = {}
            for kernels in KERNELS:
                go = _run_filter(prep, fs, np.arange(B), kernels)
                go()  # warm-up
                tm = timed(go, cfg.repeats, cfg.cheap_s)
                n = active_trial_steps(tm.result.diverged_step, K)
                rate[kernels] = n / tm.median_s
                rows.append(Row("steps", kind, f"throughput B={B}, {kernels}", rate[kernels], "trial-steps/s",
                                note=f"run_filter in-process, {B} trials x {K} steps, median of {tm.n}; "
                                     f"{n} trial-steps computed"))  # fmt: skip
            rows.append(Row("steps", kind, f"throughput B={B}: ratio compiled / numpy", rate["compiled"] / rate["numpy"],
                            "x"))  # fmt: skip
    return rows


def _features(cfg: BenchConfig) -> list[Row]:
    """Update cost per trial-step vs the number of feature points (all visible), per kernels.

    The sizes are timed in interleaved rounds (every ``N`` once per round, ``cfg.growth_rounds`` rounds, the
    best per ``N``): the exponent is a ratio of costs, and this machine's speed drifts by 10-25 % between
    minutes, which timing each size in its own minute turned into +-0.15 on the exponent; it also switches
    between two speeds ~1.5x apart within seconds (the same code, alternated: N = 48 at 4.1-4.3 ms or 6.1-6.5 ms
    per trial-step), where a median of 7 took some sizes in the slow state and others in the fast one (1.40 one
    bench, 1.54 the next, the same kernels). The best of the rounds is each size in the fast state."""
    from stereopose_mc.mc.trial import step_functions

    rows: list[Row] = []
    trials = np.arange(cfg.scaling_batch)
    for kind in cfg.filters:
        calls: dict[str, dict[int, Any]] = {k: {} for k in KERNELS}
        its: dict[int, float] = {}
        n_of: dict[int, int] = {}
        for N in cfg.feature_points:
            prep = prepare(scaling_scenario(cfg, kind, N))
            fs, s = prep.filter(kind), prep.setup
            from stereopose_mc.filters import estimators, relnav

            noisy, x0 = draws(prep, trials)
            vis = prep.exact.visible[1]
            step = relnav.StepMeasurement(y=relnav.stack_measurement(noisy.y[:, 1], vis, s.pseudo),
                                          alpha=noisy.alpha[:, 1], visible=vis, t=prep.truth.t[1])  # fmt: skip
            P0 = np.broadcast_to(np.diag(s.P0_diag), (trials.size,) + (s.x0.size,) * 2)
            P0 = estimators.initial_covariance(x0, P0, fs)
            n_of[N] = s.x0.size
            for kernels in KERNELS:
                sf = step_functions(kernels)
                with np.errstate(all="ignore"):
                    xa, Pa = sf.predict(x0, P0, prep.truth.t[0], fs, s)
                    u = sf.update(xa, Pa, step, trials, fs, s)  # warm-up (and iterations)
                its[N] = float(np.mean(u.iterations))
                calls[kernels][N] = (lambda sf=sf, xa=xa, Pa=Pa, step=step, fs=fs, s=s:
                                     sf.update(xa, Pa, step, trials, fs, s))  # fmt: skip
        for kernels in KERNELS:
            samples: dict[int, list[float]] = {N: [] for N in calls[kernels]}
            with np.errstate(all="ignore"):
                for _ in range(cfg.growth_rounds):
                    for N, go in calls[kernels].items():
                        t0 = time.perf_counter()
                        go()
                        samples[N].append((time.perf_counter() - t0) / trials.size)
            cost = {N: float(np.min(v)) for N, v in samples.items()}
            for N in sorted(cost):
                rows.append(Row("steps", kind, f"update per trial-step, N={N} (n={n_of[N]}), {kernels}", 1e6 * cost[N],
                                "us", note=f"first update of {trials.size} trials, best of {len(samples[N])} "
                                           f"interleaved rounds; mean iterations {its[N]:.2f}"))  # fmt: skip
            Ns = sorted(cost)
            p = fit_exponent(Ns, [cost[k] for k in Ns])
            tgt, st = (f"<= {TARGET_UPDATE_EXPONENT:g}", judge(p, TARGET_UPDATE_EXPONENT, "max")) \
                if kernels == "compiled" else ("", "")  # fmt: skip
            rows.append(Row("steps", kind, f"update growth exponent p ~ N^p (N={Ns[0]}..{Ns[-1]}), {kernels}", p, "",
                            tgt, st, "least squares of log(cost) on log N"))  # fmt: skip
    return rows


def _filterpy(cfg: BenchConfig) -> list[Row]:
    """FilterPy's loop against ``run_filter`` per computed step. The judged pair (FilterPy's loop, ours compiled at
    ``baseline_batch``) is timed in alternated rounds, ``baseline_rounds`` of each, medians of each: one FilterPy run
    (~2.6 s) is a single sample, and the machine's speed drifts over minutes (FilterPy's loop took 1,271-1,358 us per
    step in six runs of one stop on the same code, ours 25.7-26.4 us), so two times taken minutes apart carry that
    drift into their ratio. The other rows (numpy, ``B = baseline_trials``) are timed after, as before."""
    from .filterpy_baseline import run_trials
    prep = prepare(scenario_dict(cfg))
    s = prep.setup
    fs = prep.full_state_filter("ekf")
    T = cfg.baseline_trials
    trials = np.arange(T)
    noisy, x0 = draws(prep, trials)
    K = s.steps
    judged_batch = max(T, cfg.baseline_batch)
    judged = _run_filter(prep, fs, np.arange(judged_batch), "compiled")
    fp_s, ours_s = [], []
    with np.errstate(all="ignore"):
        for _ in range(cfg.baseline_rounds):
            t0 = time.perf_counter()
            fp_run = run_trials(x0, noisy.y, noisy.alpha, prep.exact.visible, prep.truth, s, fs)
            fp_s.append(time.perf_counter() - t0)
            judged()  # (untimed: the first run after FilterPy's loop is ~1 us per trial-step slower, measured)
            tm = timed(judged, cfg.repeats, cfg.cheap_s)
            ours_s.extend(tm.samples_s)
    fp_sps = fp_run.steps_run / statistics.median(fp_s)
    rows = [Row("steps", "ekf", "FilterPy EKF loop, per computed step", 1e6 / fp_sps, "us",
                note=f"{T} trials x {K} steps, median of {len(fp_s)} rounds alternated with the judged row's "
                     f"(FilterPy's: {', '.join(f'{t / fp_run.steps_run * 1e6:.0f}' for t in fp_s)} us)")]  # fmt: skip
    for batch in sorted({T, judged_batch}):
        for kernels in KERNELS:
            if batch == judged_batch and kernels == "compiled":
                sps = active_trial_steps(tm.result.diverged_step, K) / statistics.median(ours_s)
                tgt, st = "", ""
                per = [t / active_trial_steps(tm.result.diverged_step, K) * 1e6 for t in ours_s]
                how = (f", median of {len(ours_s)} runs ({min(per):.3g}-{max(per):.3g} us) in the {len(fp_s)} rounds "
                       f"alternated with FilterPy's")  # fmt: skip
            else:
                go = _run_filter(prep, fs, np.arange(batch), kernels)
                go()
                tm_o = timed(go, cfg.repeats, cfg.cheap_s)
                sps = active_trial_steps(tm_o.result.diverged_step, K) / tm_o.median_s
                tgt, st, how = "", "", ""
            what = f"the same {T} trials as one batch" if batch == T else \
                f"{batch} trials as one batch (an engine chunk; the first {T} are FilterPy's)"  # fmt: skip
            rows.append(Row("steps", "ekf", f"ours / FilterPy per computed step, {kernels}, B={batch}", sps / fp_sps,
                            "x", tgt, st, f"run_filter on {what}: {1e6 / sps:.3g} us per trial-step, per-step NEES "
                            f"and divergence checks included{how}"))  # fmt: skip
    batch = max(T, cfg.baseline_batch)
    parts = _split(prep, fs, np.arange(batch), "compiled")
    step_us = parts["predict"] + parts["update"]
    rows.append(Row("steps", "ekf", f"ours / FilterPy, the filter step alone (predict + update), compiled, B={batch}",
                    1e6 / fp_sps / step_us, "x",
                    note=f"an instrumented run_filter, us per trial-step: predict {parts['predict']:.3g}, update "
                    f"{parts['update']:.3g}, NEES {parts['nees']:.3g}, the rest {parts['rest']:.3g} (errors, checks, "
                    f"bookkeeping); FilterPy's loop is a filter step alone. Not the judged row"))  # fmt: skip
    return rows


def _split(prep, fs, trials, kernels) -> dict[str, float]:
    """Where ``run_filter``'s time goes, us per computed trial-step: ``predict``, ``update`` (numpy's fallback for
    trials the kernels leave to it included), ``nees`` (with the positive-definiteness check) and ``rest``; from one
    run with the three wrapped by timers (after a run that warms every cache)."""
    import types

    from stereopose_mc.mc import trial

    go = _run_filter(prep, fs, trials, kernels)
    go()
    spent = {"predict": 0.0, "update": 0.0, "nees": 0.0}
    depth = {"predict": 0, "update": 0, "nees": 0}

    def timer(f, key):  # the outermost call only (_robust_update calls itself on parts of a failed batch)
        def g(*a, **k):
            depth[key] += 1
            t0 = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                depth[key] -= 1
                if depth[key] == 0:
                    spent[key] += time.perf_counter() - t0

        return g

    stepper = trial.step_functions(kernels)
    wrapped = types.SimpleNamespace(predict=timer(stepper.predict, "predict"), update=stepper.update)
    saved = trial.step_functions, trial.nees_and_pd, trial._robust_update
    trial.step_functions, trial.nees_and_pd = (lambda k: wrapped), timer(trial.nees_and_pd, "nees")
    trial._robust_update = timer(trial._robust_update, "update")
    try:
        t0 = time.perf_counter()
        r = go()
        total = time.perf_counter() - t0
    finally:
        trial.step_functions, trial.nees_and_pd, trial._robust_update = saved
    n = active_trial_steps(r.diverged_step, prep.setup.steps)
    out = {k: v / n * 1e6 for k, v in spent.items()}
    out["rest"] = total / n * 1e6 - sum(out.values())
    return out


SECTION_FUNCS = {"e2e": e2e, "realistic": realistic, "steps": steps}
