"""The sections of the benchmark table, one function each: ``fn(cfg, tmp, ctx) -> list[Row]``.

``tmp`` is a scratch directory (scenario copies, run directories); ``ctx`` carries numbers
from one section to a later one (the campaign throughput for the baseline's ratio).
Every section benchmarks each filter type in ``cfg.filters`` of the scenario on its own.
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from . import kernels_bench
from .common import (
    active_trial_steps,
    BenchConfig,
    blas_limit,
    draws,
    engine_wall,
    first_healthy_path,
    fit_exponent,
    judge,
    log,
    percentile,
    prepare,
    Row,
    run_counts,
    scaling_scenario,
    scenario_dict,
    single_filter,
    spmc_command,
    step_latencies,
    steps_of,
    subprocess_env,
    timed,
    write_yaml,
)

# Targets (docs/performance.md): the sections here are informative but for the memory; the judged
# targets are the default command's (kernels_bench: e2e, realistic, steps)
TARGET_MEMORY_MIB = 1024.0  # 10,000 trials, peak


# ----------------------------------------------------------------------------- helpers


def spmc_run_args(scenario: Path, out: Path, trials: int, jobs: int, timeseries: str,
                  kernels: str = "compiled") -> list[str]:  # fmt: skip
    return spmc_command() + [
        "run", str(scenario), "--trials", str(trials), "--jobs", str(jobs), "--out", str(out), "--overwrite",
        "--quiet", "--no-report", "--timeseries", timeseries, "--kernels", kernels,
    ]  # fmt: skip


def _check_proc(cmd: list[str], code: int, stderr: str) -> None:
    if code != 0:
        tail = "\n".join(stderr.strip().splitlines()[-15:])
        raise RuntimeError(f"command failed with exit code {code}: {' '.join(cmd)}\n{tail}")


# ----------------------------------------------------------------------------- campaign


def campaign(cfg: BenchConfig, tmp: Path, ctx: dict[str, Any]) -> list[Row]:
    """Trials/s and wall of ``spmc run`` (subprocess, Parquet, ``--timeseries full``) per filter and ``--jobs``."""
    rows: list[Row] = []
    base = scenario_dict(cfg)
    T = cfg.campaign_trials
    reduced = T != cfg.target_trials
    env = subprocess_env(cfg)
    K = steps_of(base)
    for kind in cfg.filters:
        scn = write_yaml(tmp / f"campaign-{kind}.yaml", single_filter(base, kind))
        walls: dict[int, float] = {}
        for jobs in cfg.campaign_jobs:
            out = tmp / f"campaign-{kind}-j{jobs}"
            cmd = spmc_run_args(scn, out, T, jobs, "full")
            log(f"campaign: {kind}, {T} trials, --jobs {jobs}")
            t0 = time.perf_counter()
            r = subprocess.run(cmd, capture_output=True, text=True, env=env)
            wall = time.perf_counter() - t0
            _check_proc(cmd, r.returncode, r.stderr)
            walls[jobs] = wall
            ndiv, ntr, tsteps = run_counts(out, K)
            eng = engine_wall(out)
            rates = {"trials_per_s": T / wall, "trial_steps_per_s": tsteps / wall}
            ctx.setdefault("campaign", {})[(kind, jobs)] = rates
            target, status, note = "", "", ""
            if reduced:
                note = f"*projected {wall * cfg.target_trials / T:.1f} s for {cfg.target_trials:,} trials (linear); "
            note += (f"end to end (process start, imports, truth, Parquet); engine {eng:.1f} s; "
                     f"{ndiv}/{ntr} diverged")  # fmt: skip
            rows.append(Row("campaign", kind, f"wall, {T:,} trials, --jobs {jobs}", wall, "s", target, status, note))
            rows.append(Row("campaign", kind, f"throughput, --jobs {jobs}", T / wall, "trials/s",
                            note=f"{tsteps / wall:.0f} trial-steps/s (a diverged trial stops at its divergence step)"))
            if not cfg.keep_runs:
                _rmtree(out)
        js = sorted(walls)
        if len(js) >= 2:
            a, b = js[0], js[-1]
            rows.append(Row("campaign", kind, f"speed-up --jobs {b} vs --jobs {a}", walls[a] / walls[b], "x",
                            note=f"ideal {b / a:g}x"))  # fmt: skip
    return rows


def _rmtree(p: Path) -> None:
    import shutil

    shutil.rmtree(p, ignore_errors=True)


# ----------------------------------------------------------------------------- chunk size


def chunk_cost(cfg: BenchConfig, tmp: Path, ctx: dict[str, Any]) -> list[Row]:
    """Amortized wall time per trial of ``run_chunk`` (in-process) vs the chunk size ``B``."""
    from stereopose_mc.mc.trial import run_chunk

    rows: list[Row] = []
    prep = prepare(scenario_dict(cfg))
    K = prep.setup.steps
    for kind in cfg.filters:
        fs = prep.filter(kind)
        per: dict[int, float] = {}
        for B, total in sorted(cfg.chunk_trials.items()):
            chunks = [np.arange(s, min(s + B, total)) for s in range(0, total, B)]
            log(f"chunk: {kind}, B={B}, {total} trials")

            def go(chunks=chunks):
                return [run_chunk(prep.scenario.seed, c, prep.setup, prep.truth, prep.exact, [fs], prep.bounds)
                        for c in chunks]  # fmt: skip

            with blas_limit(cfg.inproc_threads):
                tm = timed(go, cfg.repeats, cfg.cheap_s)
            ndiv = sum(int((r.runs[0].diverged_step >= 0).sum()) for r in tm.result)
            per[B] = tm.median_s / total
            rows.append(Row("chunk", kind, f"per trial, chunk size B={B}", 1e3 * per[B], "ms/trial",
                            note=f"run_chunk in-process; {total} trials in {len(chunks)} chunk(s) of {K} steps; "
                                 f"median of {tm.n}; {ndiv}/{total} diverged"))  # fmt: skip
        if len(per) >= 2:
            b0, b1 = min(per), min(per, key=per.get)
            rows.append(Row("chunk", kind, f"amortization gain, B={b0} vs best (B={b1})", per[b0] / per[b1], "x"))
    return rows


# ----------------------------------------------------------------------------- latency


def latency(cfg: BenchConfig, tmp: Path, ctx: dict[str, Any]) -> list[Row]:
    """Wall time of one ``estimators.predict`` + ``estimators.update`` with ``B = 1``, after convergence."""
    with blas_limit(cfg.inproc_threads):
        return _latency(cfg)


def _latency(cfg: BenchConfig) -> list[Row]:
    from stereopose_mc.filters import estimators

    rows: list[Row] = []
    prep = prepare(scenario_dict(cfg))
    s = prep.setup
    K = s.steps
    k0, k1 = max(1, min(cfg.latency_steps[0], K)), min(cfg.latency_steps[1], K)
    N = s.n_points
    for kind in cfg.filters:
        fs = prep.filter(kind)
        path = first_healthy_path(prep, fs, cfg.latency_candidates)
        if path is None:
            rows.append(Row("latency", kind, "step latency", float("nan"), "ms",
                            note=f"every one of trials 0-{cfg.latency_candidates - 1} diverged"))  # fmt: skip
            continue
        trial, posts, steps, iters = path
        log(f"latency: {kind}, trial {trial}, steps {k0}-{k1}, {cfg.latency_reps} repeats")
        pred, upd = step_latencies(estimators, prep, fs, posts, steps, k0, k1, cfg.latency_reps)
        tot = np.add(pred, upd)
        med, p99 = 1e3 * float(np.median(tot)), 1e3 * percentile(tot, 99)
        it = float(np.mean(iters[k0 - 1 : k1]))
        note = (f"trial {trial}, steps {k0}-{k1}, {tot.size} samples; predict median {1e3 * np.median(pred):.3g} ms, "
                f"update median {1e3 * np.median(upd):.3g} ms; mean iterations {it:.2f}")  # fmt: skip
        rows.append(Row("latency", kind, f"step predict+update, B=1, N={N}: median", med, "ms", note=note))
        rows.append(Row("latency", kind, f"step predict+update, B=1, N={N}: p99", p99, "ms"))
    return rows


# ----------------------------------------------------------------------------- scaling


def scaling(cfg: BenchConfig, tmp: Path, ctx: dict[str, Any]) -> list[Row]:
    """Time per filter step of a batch vs the number of feature points; fitted exponent."""
    from stereopose_mc.mc.trial import run_filter

    rows: list[Row] = []
    trials = np.arange(cfg.scaling_batch)
    for kind in cfg.filters:
        per_step: dict[int, float] = {}
        for N in cfg.scaling_points:
            prep = prepare(scaling_scenario(cfg, kind, N))
            if not prep.exact.visible.all():
                raise RuntimeError(f"scaling: with N={N} points on a {cfg.sphere_radius_m} m sphere some are not "
                                   "visible; the measurement size would vary")  # fmt: skip
            fs, s = prep.filter(kind), prep.setup
            noisy, x0 = draws(prep, trials)
            log(f"scaling: {kind}, N={N}, batch {trials.size}, {s.steps} steps")

            def go():
                with np.errstate(all="ignore"):
                    return run_filter(x0, s, prep.truth, noisy.y, noisy.alpha, prep.exact.visible, fs, prep.bounds)

            with blas_limit(cfg.inproc_threads):
                tm = timed(go, cfg.repeats, cfg.cheap_s)
            r = tm.result
            K = s.steps
            per_step[N] = tm.median_s / K
            ndiv = int((r.diverged_step >= 0).sum())
            its = r.iterations[:, 1:][r.iterations[:, 1:] > 0]
            n, m = s.x0.size, 8 * N + (3 if s.pseudo else 0) + (N if s.disparity else 0)
            per_ts = tm.median_s / max(1, active_trial_steps(r.diverged_step, K))
            rows.append(Row("scaling", kind, f"time per step, N={N} (n={n}, m={m}), batch {trials.size}",
                            1e3 * per_step[N], "ms/step",
                            note=f"steps 1-{K}, median of {tm.n}; {1e6 * per_ts:.0f} us per trial-step; "
                                 f"mean iterations {its.mean() if its.size else float('nan'):.2f}; "
                                 f"{ndiv}/{trials.size} diverged; all points visible"))  # fmt: skip
        if len(per_step) >= 2:
            Ns = sorted(per_step)
            p = fit_exponent(Ns, [per_step[k] for k in Ns])
            rows.append(Row("scaling", kind, f"growth exponent p, time/step ~ N^p (N={Ns[0]}..{Ns[-1]})", p, "",
                            note="least squares of log(time/step) on log N"))  # fmt: skip
    return rows


# ----------------------------------------------------------------------------- memory


def memory(cfg: BenchConfig, tmp: Path, ctx: dict[str, Any]) -> list[Row]:
    """Peak memory of ``spmc run --timeseries summary`` (subprocess) over its process tree, Numba's cache warm
    (a 2-trial run first: the first run after an install or an edit of the kernels also holds the compiler)."""
    from .procmem import run_and_measure

    d = scenario_dict(cfg)
    label = "+".join(f.get("name") or f["type"] for f in d["filters"])
    scn = write_yaml(tmp / "memory.yaml", d)
    out = tmp / "memory-run"
    T, J = cfg.memory_trials, cfg.memory_jobs
    cmd = spmc_run_args(scn, out, T, J, "summary", cfg.memory_kernels)
    if cfg.memory_kernels == "compiled":  # Numba's cache warm first: the row is the run's memory, not the compiler's
        warm = spmc_run_args(scn, tmp / "memory-warm-up", 2, 1, "summary", "compiled")
        log("memory: warm-up (2 trials: compiles the kernels if their cache is cold)")
        r = subprocess.run(warm, capture_output=True, text=True, env=subprocess_env(cfg))
        _check_proc(warm, r.returncode, r.stderr)
        _rmtree(tmp / "memory-warm-up")
    log(f"memory: {T} trials, --jobs {J}, --timeseries summary, --kernels {cfg.memory_kernels}, filters {label}")
    pm = run_and_measure(cmd, cfg.memory_interval_s, env=subprocess_env(cfg))
    _check_proc(cmd, pm.returncode, pm.stderr)
    ndiv, ntr, _ = run_counts(out, steps_of(d))
    if not cfg.keep_runs:
        _rmtree(out)
    reduced = T != cfg.memory_target_trials
    how = f"sum over the process tree, /proc sampled every {pm.interval_s:g} s ({pm.samples} samples, " \
          f"up to {pm.max_processes} processes)"
    star = f"*measured at {T:,} trials, not projected; " if reduced else ""
    return [
        Row("memory", label, f"peak RSS, {T:,} trials, --jobs {J}, {cfg.memory_kernels}", pm.tree_rss_mib, "MiB",
            f"<= {TARGET_MEMORY_MIB:g} MiB ({cfg.memory_target_trials:,} trials)",
            judge(pm.tree_rss_mib, TARGET_MEMORY_MIB, "max", reduced),
            star + how + "; shared pages counted per process"),
        Row("memory", label, "peak PSS (shared pages split)", pm.tree_pss_mib, "MiB", note=how),
        Row("memory", label, "largest single process RSS", pm.wait4_maxrss_mib, "MiB",
            note="ru_maxrss from os.wait4 (kernel-tracked, no sampling); "
                 f"sampled: {pm.sampled_max_process_rss_mib:.0f} MiB"),
        Row("memory", label, "wall of that run (--timeseries summary)", pm.wall_s, "s",
            note=f"{T / pm.wall_s:.1f} trials/s with all filters; {ndiv} of {ntr} (trial, filter) runs diverged"),
    ]  # fmt: skip


# ----------------------------------------------------------------------------- FilterPy baseline


def baseline(cfg: BenchConfig, tmp: Path, ctx: dict[str, Any]) -> list[Row]:
    """Per-trial FilterPy EKF vs our batched EKF on the same trials; throughput ratio.

    Throughputs are compared per trial-step: the FilterPy loop runs every step of every
    trial, while the engine stops a trial at its divergence step.
    """
    from stereopose_mc.mc.trial import run_filter

    from .filterpy_baseline import run_trials

    rows: list[Row] = []
    prep = prepare(scenario_dict(cfg))
    s = prep.setup
    fs = prep.full_state_filter("ekf")
    T = cfg.baseline_trials
    trials = np.arange(T)
    noisy, x0 = draws(prep, trials)
    K = s.steps
    log(f"baseline: FilterPy EKF, {T} trials x {K} steps")
    with np.errstate(all="ignore"), blas_limit(cfg.inproc_threads):
        fp = timed(lambda: run_trials(x0, noisy.y, noisy.alpha, prep.exact.visible, prep.truth, s, fs),
                   cfg.repeats, cfg.cheap_s)  # fmt: skip
        ours = timed(lambda: run_filter(x0, s, prep.truth, noisy.y, noisy.alpha, prep.exact.visible, fs, prep.bounds),
                     cfg.repeats, cfg.cheap_s)  # fmt: skip
    b, o = fp.result, ours.result
    fp_steps, our_steps = b.steps_run, active_trial_steps(o.diverged_step, K)
    fp_sps, our_sps = fp_steps / fp.median_s, our_steps / ours.median_s
    ndiv_o, nstop = int((o.diverged_step >= 0).sum()), int((b.stopped_step >= 0).sum())
    rows.append(Row("baseline", "ekf", "FilterPy ExtendedKalmanFilter, per-trial loop: throughput", T / fp.median_s,
                    "trials/s",
                    note=f"{T} trials x {K} steps, median of {fp.n}; {fp_sps:.0f} trial-steps/s "
                         f"({1e3 / fp_sps:.3g} ms per step); every step run "
                         f"({nstop} stopped on non-finite/singular S); "
                         "FilterPy has no IEKF: EKF vs our EKF"))  # fmt: skip
    rows.append(Row("baseline", "ekf", f"our EKF in-process, the same {T} trials as one batch: throughput",
                    T / ours.median_s, "trials/s",
                    note=f"run_filter, median of {ours.n}; {our_sps:.0f} trial-steps/s; {ndiv_o}/{T} trials "
                         f"diverged (engine test) and stopped early"))  # fmt: skip
    # agreement: the errors of both at the steps both computed
    e_fp, e_o = b.errors[:, 1:], o.errors[:, 1:]
    both = np.isfinite(e_fp).all(-1) & np.isfinite(e_o).all(-1)
    rel = np.abs(e_fp - e_o) / np.maximum(np.abs(e_o), 1e-300)
    first = float(np.max(rel[:, 0][both[:, 0]])) if both[:, 0].any() else float("nan")
    med = float(np.median(rel[both])) if both.any() else float("nan")
    rows.append(Row("baseline", "ekf", "agreement: max relative difference of the errors at the first update",
                    first, "", note=f"median over all {int(both.sum())} trial-steps both computed: {med:.2g}; "
                                    "inv(S) vs solve and expm vs Taylor-4 round-off in an ill-conditioned S "
                                    "(filter R ~1e-10 vs prior P ~1) grows through the nonlinear "
                                    "transient"))  # fmt: skip
    camp = ctx.get("campaign", {})
    if ("ekf", 1) in camp:
        c = camp[("ekf", 1)]
        ratio = c["trial_steps_per_s"] / fp_sps
        others = "; ".join(f"--jobs {j}: {v['trial_steps_per_s'] / fp_sps:.1f}x" for (k, j), v in sorted(camp.items())
                           if k == "ekf" and j != 1)  # fmt: skip
        note = (f"campaign EKF --jobs 1 (end to end incl. start-up and Parquet), per trial-step; per trial: "
                f"{c['trials_per_s'] / (T / fp.median_s):.1f}x" + (f"; {others}" if others else ""))
    else:
        ratio = our_sps / fp_sps
        note = f"in-process, same {T} trials, per trial-step (campaign section not run)"
    rows.append(Row("baseline", "ekf", "throughput ratio ours / FilterPy", ratio, "x", note=note))
    if ("ekf", 1) in camp:
        rows.append(Row("baseline", "ekf", "throughput ratio, in-process, same trials", our_sps / fp_sps, "x",
                        note=f"run_filter on the same {T} trials as one batch, per trial-step"))  # fmt: skip
    return rows


# ----------------------------------------------------------------------------- dispersed truth

TARGET_TRUTH_SHARE = 0.20  # the per-trial truth's share of a dispersed campaign (issue 11)
DISPERSED_TRIALS = {"full": 50, "quick": 10}  # one chunk


def dispersed_truth(cfg: BenchConfig, tmp: Path, ctx: dict[str, Any]) -> list[Row]:
    """Share of the per-trial truth (draws, validation, batched DOP853, exact measurements) in a dispersed chunk.

    The benchmark scenario with configs/mission-debris.yaml's ``dispersions`` block; one chunk,
    both filters, in-process (``mc.dispersed.run_chunk``).
    """
    import yaml

    from stereopose_mc.config.resolve import setup_of
    from stereopose_mc.mc import dispersed
    from stereopose_mc.sim import dispersions as sd

    d = scenario_dict(cfg)
    d["dispersions"] = yaml.safe_load((Path(__file__).resolve().parents[1] / "configs" / "mission-debris.yaml")
                                      .read_text())["dispersions"]  # fmt: skip
    prep = prepare(d)
    B = DISPERSED_TRIALS.get(cfg.mode, 10)
    trials = np.arange(B)
    log(f"dispersed: one chunk of {B} trials")

    def truth_part():
        draw = sd.draw(prep.scenario, trials)
        setups = [setup_of(s) for s in draw.truth if s is not None]
        return sd.exact_measurements(setups, sd.truth_of(setups, prep.setup.times, prep.setup.truth_rtol))

    with blas_limit(cfg.inproc_threads):
        t_truth = timed(truth_part, cfg.repeats, cfg.cheap_s)
        t_all = timed(lambda: dispersed.run_chunk(prep.scenario, trials, prep.setup, prep.bounds), cfg.repeats,
                      cfg.cheap_s)  # fmt: skip
    share = t_truth.median_s / t_all.median_s
    filters = "+".join(f.label for f in prep.filters)
    return [
        Row("dispersed", filters, f"truth per trial, chunk of {B}", 1e3 * t_truth.median_s / B, "ms/trial",
            note="draw + validate + setups + batched DOP853 + exact measurements"),
        Row("dispersed", filters, f"campaign per trial, chunk of {B}", 1e3 * t_all.median_s / B, "ms/trial",
            note="mc.dispersed.run_chunk, every filter"),
        Row("dispersed", filters, "truth share of a dispersed campaign", 100 * share, "%",
            target=f"<= {100 * TARGET_TRUTH_SHARE:g} %", status=judge(share, TARGET_TRUTH_SHARE, "max", cfg.mode != "full"),
            note=f"medians of {t_truth.n} and {t_all.n}"),
    ]  # fmt: skip


SECTION_FUNCS: dict[str, Callable[[BenchConfig, Path, dict], list[Row]]] = {
    "campaign": campaign,
    "chunk": chunk_cost,
    "latency": latency,
    "scaling": scaling,
    "memory": memory,
    "baseline": baseline,
    "dispersed": dispersed_truth,
    **kernels_bench.SECTION_FUNCS,  # issue 14: numpy vs compiled kernels
}
