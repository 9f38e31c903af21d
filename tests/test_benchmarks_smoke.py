"""Smoke test of the benchmark harness (benchmarks/): every section runs at minimal size.

No timing is asserted. What is checked: each section yields its table rows with finite
positive values and a valid status; the FilterPy baseline (an independent EKF written with
FilterPy's inv-based gain and expm transition) ends at the same state as our EKF; the
memory sampler sees a known allocation; the exponent fit recovers a known power; the
CSV/JSON outputs hold the rows.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import common, sections  # noqa: E402
from benchmarks.procmem import run_and_measure  # noqa: E402

TINY_TIME = {"dt_s": 1.0, "duration_s": 3.0, "error_window_start_s": 0.0}


@pytest.fixture(scope="module")
def cfg(tmp_path_factory):
    return common.BenchConfig(
        mode="smoke", out=tmp_path_factory.mktemp("bench"), time_override=TINY_TIME, repeats=1,
        campaign_trials=2, realistic_trials=2, campaign_jobs=(1, 2), chunk_trials={1: 2, 2: 2}, latency_steps=(2, 3), latency_reps=1,
        latency_candidates=3, scaling_points=(5, 6), scaling_batch=2, scaling_steps=2, memory_trials=2, memory_jobs=1,
        memory_interval_s=0.05, baseline_trials=2, baseline_batch=3, feature_points=(5, 6), cold_cache=False,
    )  # fmt: skip


@pytest.fixture(scope="module")
def results(cfg):
    tmp = cfg.out / "tmp"
    tmp.mkdir()
    ctx: dict = {}
    rows = {name: fn(cfg, tmp, ctx) for name, fn in sections.SECTION_FUNCS.items()}
    return rows, ctx


def _measures(rows):
    return [(r.filter, r.measure) for r in rows]


def test_every_section_yields_finite_rows(results):
    rows, _ = results
    assert set(rows) == set(common.SECTIONS)
    for name, rs in rows.items():
        assert rs, name
        for r in rs:
            assert r.section == name
            assert r.status in ("", "met", "not met", "met*", "not met*"), r
            assert (r.status == "") == (r.target == ""), r
            assert math.isfinite(r.value), r
            if r.unit not in ("", "SI"):
                assert r.value > 0, r


def test_campaign_rows(results, cfg):
    rows, ctx = results
    m = _measures(rows["campaign"])
    for kind in ("iekf", "ekf"):
        for j in (1, 2):
            assert (kind, f"wall, 2 trials, --jobs {j}") in m
            assert (kind, f"throughput, --jobs {j}") in m
        assert (kind, "speed-up --jobs 2 vs --jobs 1") in m
    wall = {(r.filter, r.measure): r.value for r in rows["campaign"]}
    # throughput is trials / wall of the same run
    assert wall[("ekf", "throughput, --jobs 1")] == pytest.approx(2 / wall[("ekf", "wall, 2 trials, --jobs 1")])
    c = ctx["campaign"][("ekf", 1)]
    assert c["trials_per_s"] == pytest.approx(wall[("ekf", "throughput, --jobs 1")])
    # 3 steps per trial; a diverged trial stops early, so at most 3 trial-steps per trial
    assert 0 < c["trial_steps_per_s"] <= 3 * c["trials_per_s"] * (1 + 1e-12)
    assert not [r for r in rows["campaign"] if r.target]  # informative: the judged campaigns are e2e's and realistic's


def test_chunk_latency_scaling_rows(results):
    rows, _ = results
    m = _measures(rows["chunk"])
    for kind in ("iekf", "ekf"):
        assert (kind, "per trial, chunk size B=1") in m and (kind, "per trial, chunk size B=2") in m
    lat = [r for r in rows["latency"] if r.measure.endswith("median")]
    assert {r.filter for r in lat} == {"iekf", "ekf"}
    assert all(r.target == "" for r in lat)  # informative
    sc = rows["scaling"]
    assert {r.measure for r in sc if "N=5 " in r.measure} == {"time per step, N=5 (n=30, m=43), batch 2"}
    assert {r.measure for r in sc if "N=6 " in r.measure} == {"time per step, N=6 (n=33, m=51), batch 2"}
    expo = [r for r in sc if r.measure.startswith("growth exponent")]
    assert len(expo) == 2 and all(r.target == "" for r in expo)


def test_memory_rows(results):
    rows, _ = results
    rs = {r.measure: r for r in rows["memory"]}
    rss = rs["peak RSS, 2 trials, --jobs 1, compiled"]
    assert rss.filter == "iekf+ekf"
    # a Python process with numpy, pandas and pyarrow loaded holds well over 50 MiB and the
    # tree sum is at least the largest single process seen while sampling
    assert 50 < rss.value < 4096
    assert rs["peak PSS (shared pages split)"].value <= rss.value + 1.0
    assert rs["largest single process RSS"].value > 50


def test_baseline_rows(results):
    rows, _ = results
    rs = {r.measure: r for r in rows["baseline"]}
    agree = rs["agreement: max relative difference of the errors at the first update"]
    # same EKF equations from identical inputs: only round-off differs at the first update
    assert agree.value < 1e-4
    ratio = rs["throughput ratio ours / FilterPy"]
    assert ratio.target == "" and ratio.note.startswith("campaign EKF --jobs 1")


def test_filterpy_step_equals_ours_from_the_same_inputs(cfg):
    """One FilterPy predict + update equals relnav.predict + relnav.update (independent code)."""
    from scipy.linalg import expm

    from stereopose_mc.core import jacobians
    from stereopose_mc.core.orbit import leader_kinematics
    from stereopose_mc.filters import relnav

    from benchmarks import filterpy_baseline as fb

    prep = common.prepare(common.scenario_dict(cfg))
    # ours with the exact transition (the scenario's default is a Taylor series) to isolate the code
    s, fs = prep.setup, dataclasses.replace(prep.full_state_filter("ekf"), transition="expm")
    noisy, x0 = common.draws(prep, np.arange(1))
    P0 = np.diag(s.P0_diag)
    vis = prep.exact.visible[1]
    step = relnav.StepMeasurement(y=relnav.stack_measurement(noisy.y[:, 1], vis, s.pseudo), alpha=noisy.alpha[:, 1],
                                  visible=vis, t=prep.truth.t[1])  # fmt: skip
    xa, Pa = relnav.predict(x0, P0[None], 0.0, fs, s)
    u = relnav.update(xa, Pa, step, np.arange(1), fs, s)

    ekf = fb.RelNavEKF(x0.shape[1], 43, s.orbit, s.dt, fs.substeps)
    ekf.x, ekf.P, ekf.Q = x0[0][:, None].copy(), P0.copy(), np.diag(fs.Q_diag)
    lk0 = leader_kinematics(s.orbit, 0.0)
    ekf.F = expm(jacobians.F(ekf.x[:, 0], lk0.r, lk0.nu_dot, lk0.nu_ddot, s.orbit.mu) * s.dt)
    ekf.predict()
    np.testing.assert_allclose(ekf.x[:, 0], xa[0], rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(ekf.P, Pa[0], rtol=0, atol=1e-13 * np.abs(Pa).max())
    lk = leader_kinematics(s.orbit, 1.0)
    z = np.concatenate([noisy.y[0, 1][vis].ravel(), np.zeros(3)])
    R = np.diag(relnav.measurement_noise(fs, s, int(vis.sum())))
    args = (vis, noisy.alpha[0, 1], lk.nu_dot, lk.nu_ddot, s)
    ekf.x, ekf.P = xa[0][:, None].copy(), Pa[0].copy()  # isolate the update
    ekf.update(z[:, None], fb.h_jacobian, fb.hx, R=R, args=args, hx_args=args)
    ekf.x[9:13] /= np.linalg.norm(ekf.x[9:13])
    dx = np.abs(u.x[0] - xa[0]).max()
    assert dx > 0.1  # a real correction
    # S has condition number ~1e10 (R ~1e-10, H P H^T ~1): inv vs solve differ at ~1e-6 of the step
    np.testing.assert_allclose(ekf.x[:, 0], u.x[0], rtol=0, atol=1e-5 * dx)
    np.testing.assert_allclose(ekf.P, u.P[0], rtol=0, atol=1e-6 * np.abs(u.P[0]).max())


def test_filterpy_run_tracks_ours(cfg):
    from stereopose_mc.mc.trial import run_filter

    from benchmarks.filterpy_baseline import run_trials

    prep = common.prepare(common.scenario_dict(cfg))
    fs = prep.full_state_filter("ekf")  # FilterPy's EKF is the full-state (additive) one
    noisy, x0 = common.draws(prep, np.arange(2))
    b = run_trials(x0, noisy.y, noisy.alpha, prep.exact.visible, prep.truth, prep.setup, fs)
    o = run_filter(x0, prep.setup, prep.truth, noisy.y, noisy.alpha, prep.exact.visible, fs, prep.bounds)
    assert b.steps_run == 2 * prep.setup.steps and (b.stopped_step < 0).all()
    both = np.isfinite(o.errors).all(-1)
    np.testing.assert_allclose(b.errors[both], o.errors[both], rtol=1e-3)


def test_procmem_sees_a_known_allocation():
    """A child touching 256 MiB is measured at 256-512 MiB, however big the parent is.

    The parent (this process) first touches 640 MiB: a child forked and exec'ed directly
    from it would inherit that high-water mark in ``ru_maxrss``; the launcher prevents it.
    """
    big = np.ones(80 * 2**20)  # 640 MiB, touched
    code = "import time, numpy as np; a = np.ones(32 * 2**20); time.sleep(0.6)"  # 256 MiB, touched
    pm = run_and_measure([sys.executable, "-c", code], interval_s=0.05)
    del big
    assert pm.returncode == 0
    assert 256 <= pm.tree_rss_mib < 512
    assert 256 <= pm.wait4_maxrss_mib < 512
    assert pm.max_processes == 1  # the launcher is not counted


def test_fit_exponent_recovers_a_power_law():
    N = np.array([5.0, 10.0, 20.0, 50.0])
    assert common.fit_exponent(N, 3e-4 * N**2.5) == pytest.approx(2.5, abs=1e-12)
    assert common.fit_exponent(N, 7.0 * N) == pytest.approx(1.0, abs=1e-12)


def test_sphere_points_on_the_sphere_and_spread():
    p = common.sphere_points(50, 1.5)
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), 1.5, rtol=1e-12)
    assert abs(p.mean(axis=0)).max() < 0.1 * 1.5  # evenly spread: centroid near the centre
    d = np.linalg.norm(p[:, None] - p[None], axis=-1) + np.eye(50) * 10
    assert d.min() > 0.3  # no two points coincide


def test_judge_and_percentile():
    assert common.judge(29.9, 30, "max") == "met" and common.judge(30.1, 30, "max") == "not met"
    assert common.judge(12, 10, "min", reduced=True) == "met*"
    assert common.judge(float("nan"), 10, "min") == "not met"
    assert common.percentile([4.0, 1.0, 3.0, 2.0], 50) == 2.0  # an actual sample


def test_outputs_hold_the_rows(results, tmp_path):
    rows, _ = results
    flat = [r for rs in rows.values() for r in rs]
    text = common.format_table(flat)
    lines = text.splitlines()
    assert len(lines) == len(flat) + 2 and lines[0].startswith("| section")
    c, j = common.write_outputs(flat, {"mode": "smoke"}, tmp_path / "b", "results-smoke")
    with c.open() as fh:
        back = list(csv.DictReader(fh))
    assert len(back) == len(flat)
    assert float(back[0]["value"]) == flat[0].value
    payload = json.loads(j.read_text())
    assert payload["mode"] == "smoke" and len(payload["rows"]) == len(flat)


def test_kernel_sections_measure_the_default_command(results):
    rows, _ = results
    e2e = {r.measure: r for r in rows["e2e"]}
    warm = e2e["wall, 2 trials, default command, warm"]
    assert warm.target == "<= 5 s (1,000 trials)" and warm.status.endswith("*")  # projected from 2 trials
    ref = e2e["wall, 2 trials, --kernels numpy (the reference), warm"]
    assert e2e["ratio numpy / compiled (warm, default jobs)"].value == pytest.approx(ref.value / warm.value)
    assert "2-trial run, warm, default command: median" in e2e and "spmc --help, warm: median" in e2e
    demo = e2e["make demo's command (spmc run configs/caseB.yaml: 2 trials and the report), warm"]  # informative
    assert demo.target == "" and demo.value > 0
    assert "the report alone (spmc report of that run, after it)" in demo.note
    own = e2e.get("wall, 2 trials, default command, warm, OpenBLAS's own kernels")  # informative, where it is set
    assert (own is not None) == bool(os.environ.get("OPENBLAS_CORETYPE"))
    assert own is None or (own.target == "" and own.value > 0 and "alternated with the judged row's runs" in own.note)
    real = {r.measure.split(":")[0]: r for r in rows["realistic"]}
    assert set(real) == {"mission-realistic", "mission-mesh-dispersed"}
    assert real["mission-realistic"].target == "<= 30 s (1,000 trials)"
    assert real["mission-mesh-dispersed"].target == "<= 60 s (1,000 trials)"
    assert real["mission-mesh-dispersed"].filter == "iekf+mekf"
    st = {(r.filter, r.measure): r for r in rows["steps"]}
    for kind in ("iekf", "ekf"):
        assert st[(kind, "latency B=1, step predict+update, compiled: median")].target == ""  # informative
        for B in (1, 2):
            assert (kind, f"throughput B={B}: ratio compiled / numpy") in st
        assert (kind, "update growth exponent p ~ N^p (N=5..6), compiled") in st
    assert st[("ekf", "ours / FilterPy per computed step, compiled, B=3")].target == ""  # informative
    assert st[("ekf", "ours / FilterPy per computed step, compiled, B=2")].target == ""  # FilterPy's own trials
    # the judged pair timed in alternated rounds (cfg.baseline_rounds, 3 by default): FilterPy's per-round times in
    # its note, their median its value; the judged row's median over its runs in those rounds
    fp_row = st[("ekf", "FilterPy EKF loop, per computed step")]
    per_round = [float(v) for v in re.search(r"FilterPy's: ([0-9, ]+) us", fp_row.note).group(1).split(",")]
    assert len(per_round) == 3 and "median of 3 rounds" in fp_row.note
    assert fp_row.value == pytest.approx(float(np.median(per_round)), rel=1e-2, abs=1.0)  # (notes round to 1 us)
    assert "in the 3 rounds alternated with FilterPy's" in st[("ekf", "ours / FilterPy per computed step, compiled, B=3")].note
    # the judged row's time split, and the filter step alone against FilterPy (not judged)
    alone = st[("ekf", "ours / FilterPy, the filter step alone (predict + update), compiled, B=3")]
    assert alone.target == "" and np.isfinite(alone.value) and alone.value > 0
    split = dict(re.findall(r"(predict|update|NEES|the rest) ([-0-9.e+]+)", alone.note))
    assert set(split) == {"predict", "update", "NEES", "the rest"}
    fp = st[("ekf", "FilterPy EKF loop, per computed step")].value
    assert alone.value == pytest.approx(fp / (float(split["predict"]) + float(split["update"])), rel=5e-3)  # the note's 3 digits
    assert float(split["predict"]) > 0 and float(split["update"]) > 0 and float(split["NEES"]) > 0


def test_profile_map_names_the_loaded_kernels_where_they_were_loaded(tmp_path):
    """benchmarks/profile_kernels.py --map-only: perf's JIT map lists the kernels' functions (the update kernel of
    case B's run among them), one range each, none overlapping another, in the process's own JIT memory."""
    import subprocess

    script = (
        "import os, runpy, sys; sys.argv = ['profile_kernels.py', %r, '--map-only']; "
        "code = 0\n"
        "try:\n    runpy.run_path(%r, run_name='__main__')\n"
        "except SystemExit as e:\n    code = e.code\n"
        "print('PID', os.getpid()); sys.exit(code)"
    ) % (str(ROOT / "configs" / "caseB.yaml"), str(ROOT / "benchmarks" / "profile_kernels.py"))
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path,
                         timeout=600)  # fmt: skip
    assert out.returncode == 0, out.stderr
    pid = int(re.search(r"PID (\d+)", out.stdout).group(1))
    path = Path(f"/tmp/perf-{pid}.map")
    lines = path.read_text().splitlines()
    rows = [(int(a, 16), int(s, 16), name) for a, s, name in (ln.split(" ", 2) for ln in lines)]
    path.unlink()
    names = {name for *_, name in rows}
    assert "stereopose_mc::core::kernels::update::iekf_update_batch" in names
    assert all(a > 0 and s > 0 for a, s, _ in rows) and len(rows) > 50
    assert all(a0 + s0 <= a1 for (a0, s0, _), (a1, _, _) in zip(rows, rows[1:]))  # (sorted, disjoint)
