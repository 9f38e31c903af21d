"""Chunks in workers forked from the driver (``mc/forked.py``): results, errors, dead workers, locks, progress."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from stereopose_mc.config import load_scenario
from stereopose_mc.mc import engine, forked, progress
from stereopose_mc.rundir import runlock
from stereopose_mc.rundir.store import RunDirError

from scenarios import write_scenario

pytestmark = pytest.mark.skipif(not forked.available(), reason="forked workers: Linux only")

SHORT = {"dt_s": 1.0, "duration_s": 6.0, "error_window_start_s": 1.0}


def test_every_chunk_is_computed_once_in_a_worker_and_returned():
    driver = os.getpid()
    got = list(forked.outputs(lambda i: (i, i * i, os.getpid(), os.getppid()), 7, 2))
    assert sorted(r[:2] for r in got) == [(i, i * i) for i in range(7)]
    pids = {r[2] for r in got}
    assert driver not in pids and 1 <= len(pids) <= 2 and {r[3] for r in got} == {driver}


def test_a_closure_reaches_the_workers_through_the_fork_not_pickling():
    import threading

    lock = threading.Lock()  # not picklable: a spawned worker could not receive it
    assert list(forked.outputs(lambda i: lock.locked(), 1, 2)) == [False]


def test_an_exception_in_a_chunk_is_raised_in_the_driver():
    def job(i):
        if i == 2:
            raise ValueError("chunk 2 is bad")
        return i

    with pytest.raises(ValueError, match="chunk 2 is bad"):
        list(forked.outputs(job, 4, 2))


def test_a_worker_that_dies_is_named_by_its_chunk():
    def job(i):
        if i == 1:
            os._exit(3)  # as if killed (out of memory)
        time.sleep(0.2)
        return i

    with pytest.raises(forked.WorkerDied, match=r"died while computing chunk (trials \d+-\d+ or )?trials 10-19"):
        list(forked.outputs(job, 3, 2, names=["trials 0-9", "trials 10-19", "trials 20-29"]))


def test_init_runs_once_in_each_worker_before_its_chunks():
    import multiprocessing

    started = multiprocessing.get_context("fork").RawValue("q", 0)

    def init():
        started.value += 1  # (a shared int: each worker adds one)

    out = list(forked.outputs(lambda i: started.value >= 1, 4, 2, init=init))
    assert out == [True] * 4 and 1 <= started.value <= 2


def test_a_worker_holds_none_of_the_drivers_run_locks(tmp_path):
    """A ``flock`` belongs to the open file a fork shares: the workers close their copies, so the driver's
    release frees the directory while a worker still runs, and a worker's copy never keeps it locked."""
    fd = runlock.acquire(tmp_path, "test")

    def job(i):
        held = sorted(runlock._HELD)
        time.sleep(0.1 if i == 0 else 2.0)
        return i, held

    it = forked.outputs(job, 2, 2)
    try:
        first = next(it)  # chunk 0; chunk 1's worker sleeps on
        assert first == (0, [])
        with pytest.raises(RunDirError, match="is in use by pid"):
            runlock.acquire(tmp_path, "second")  # the driver still holds it
        runlock.release(fd)
        again = runlock.acquire(tmp_path, "after")  # not held by the sleeping worker
        runlock.release(again)
        assert next(it) == (1, [])
    finally:
        it.close()


def test_shared_steps_are_the_step_counters_mapping_across_the_fork():
    steps = progress.SharedSteps([0, 10], ["iekf", "ekf"])

    def job(i):
        key = (0, 10)[i]
        tick = progress.StepCounter.tick_of(steps, key)
        tick(5 + i, "ekf", i)
        tick(7)
        return i

    assert sorted(forked.outputs(job, 2, 2)) == [0, 1]
    c = progress.StepCounter(steps)
    assert c.total() == (5 + 7) + (6 + 7)
    assert c.lost(set()) == {"iekf": 0, "ekf": 1} and c.lost({10}) == {"iekf": 0, "ekf": 0}
    assert steps[0] == 12 and steps[(10, "ekf")] == 1
    with pytest.raises(KeyError):
        steps[5] = 1  # not a chunk of this run
    with pytest.raises(KeyError):
        steps[(0, "ukf")] = 1  # not one of its filters


def test_a_run_on_forked_workers_counts_progress_and_matches_threads(tmp_path):
    from stereopose_mc import api

    scn = load_scenario(write_scenario(tmp_path / "s.yaml", trials=12, time=SHORT))
    calls: list[tuple[int, int, dict]] = []
    a = api.run(scn, out=tmp_path / "fork", jobs=2, chunk_size=3, backend="fork",
                progress=lambda done, total, div: calls.append((done, total, dict(div))))  # fmt: skip
    b = api.run(scn, out=tmp_path / "threads", jobs=2, chunk_size=3, backend="threading")
    for name in ("trials.parquet", "timeseries.parquet", "percentiles.csv"):
        assert (tmp_path / "fork" / name).read_bytes() == (tmp_path / "threads" / name).read_bytes(), name
    assert calls[-1][:2] == (12, 12) and calls[-1][2] == {k: int(v) for k, v in
                                                          a.trials.groupby("filter")["diverged"].sum().items()}
    assert b.trials.equals(a.trials)


def test_a_worker_that_dies_in_a_run_is_a_run_error_and_the_finished_chunks_stay(tmp_path, monkeypatch):
    from stereopose_mc import api
    from stereopose_mc.api.errors import SpmcError

    scn = load_scenario(write_scenario(tmp_path / "s.yaml", trials=8, time=SHORT))
    real = engine.compute_chunk

    def compute(scenario_json, trials, *args, **kwargs):
        if int(trials[0]) == 6:
            time.sleep(0.5)  # the others are written by now
            os._exit(9)
        return real(scenario_json, trials, *args, **kwargs)

    monkeypatch.setattr(engine, "compute_chunk", compute)
    out = tmp_path / "run"
    with pytest.raises(SpmcError, match=r"died while computing chunk (trials \d-\d or )?trials 6-7 .*run --resume"):
        api.run(scn, out=out, jobs=2, chunk_size=2, backend="fork")
    assert {p.name for p in (out / "chunks").glob("chunk-*.json")} == {
        f"chunk-{a:07d}-{a + 1:07d}.json" for a in (0, 2, 4)}  # fmt: skip
    monkeypatch.undo()
    r = api.resume(out)
    assert np.array_equal(np.unique(r.trials["trial"]), np.arange(8))


def _children(pid: int) -> list[int]:
    """The live (not zombie) processes whose parent is ``pid`` (from ``/proc``)."""
    out = []
    for status in Path("/proc").glob("[0-9]*/status"):
        try:
            fields = dict(line.split(":\t", 1) for line in status.read_text().splitlines() if ":\t" in line)
        except OSError:  # gone meanwhile
            continue
        if fields.get("PPid", "").strip() == str(pid) and not fields.get("State", "").startswith("Z"):
            out.append(int(status.parent.name))
    return out


def _alive(pid: int) -> bool:
    try:
        return not (Path("/proc") / str(pid) / "stat").read_text().split(") ", 1)[1].startswith("Z")
    except (OSError, IndexError):
        return False


def test_the_workers_die_with_a_driver_killed_by_sigkill(tmp_path):
    """PR_SET_PDEATHSIG: a driver killed outright (no handler runs) leaves no worker computing into its run."""
    scn = write_scenario(tmp_path / "s.yaml", trials=400, time=SHORT)
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "stereopose_mc.cli.main", "run", str(scn), "--out", str(out), "--chunk-size", "2",
           "--jobs", "2", "--backend", "fork", "--quiet", "--no-report"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 120
        while time.time() < deadline and not list(out.glob("chunks/trials-*.parquet")):
            time.sleep(0.01)
        workers = _children(proc.pid)
        assert len(workers) >= 2, "the run's workers were not found (or the run had ended)"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        deadline = time.time() + 10
        while time.time() < deadline and any(_alive(w) for w in workers):
            time.sleep(0.01)
        assert not [w for w in workers if _alive(w)]
        assert not (out / "trials.parquet").exists()
    finally:
        if proc.poll() is None:
            proc.kill()
