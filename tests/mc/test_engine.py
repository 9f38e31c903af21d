"""The Monte Carlo engine: determinism across jobs/chunks/backends, resume, refusal."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from stereopose_mc.cli.main import app

from scenarios import write_scenario

runner = CliRunner()
SHORT = {"dt_s": 1.0, "duration_s": 20.0, "error_window_start_s": 5.0}


def spmc(*args):
    return runner.invoke(app, [str(a) for a in args])


def run_ok(*args):
    r = spmc(*args, "--quiet", "--no-report")
    assert r.exit_code == 0, r.output
    return r


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    d = tmp_path_factory.mktemp("scn")
    return write_scenario(d / "s.yaml", trials=8, time=SHORT)


@pytest.fixture(scope="module")
def reference(scenario, tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "run"
    run_ok("run", scenario, "--out", out, "--jobs", 1, "--chunk-size", 8)
    return out


def same_bytes(a: Path, b: Path, names=("trials.parquet", "timeseries.parquet", "percentiles.csv")):
    for n in names:
        assert (a / n).read_bytes() == (b / n).read_bytes(), n


@pytest.mark.parametrize("jobs,chunk", [(2, 3), (1, 1), (2, 5)])
def test_same_bytes_for_any_jobs_and_chunk_size(scenario, reference, tmp_path, jobs, chunk):
    out = tmp_path / "run"
    run_ok("run", scenario, "--out", out, "--jobs", jobs, "--chunk-size", chunk)
    same_bytes(reference, out)


def test_threading_backend_same_bytes(scenario, reference, tmp_path):
    out = tmp_path / "run"
    run_ok("run", scenario, "--out", out, "--jobs", 2, "--chunk-size", 4, "--backend", "threading")
    same_bytes(reference, out)


def test_run_directory_contents(reference):
    for n in ("config.yaml", "manifest.json", "trials.parquet", "timeseries.parquet", "timing.parquet",
              "percentiles.csv", "percentiles.md", "percentiles.parquet"):  # fmt: skip
        assert (reference / n).is_file(), n
    t = pd.read_parquet(reference / "trials.parquet")
    assert list(t["trial"].unique()) == list(range(8))
    assert set(t["filter"]) == {"iekf", "ekf"}
    for col in ("trial", "filter", "seed", "e_rho", "e_rho_dot", "e_omega", "e_theta", "e_k1", "e_k2",
                "final_e_rho", "diverged", "diverged_step", "diverged_reason", "iterations_mean"):  # fmt: skip
        assert col in t.columns
    import pyarrow.parquet as pq

    md = pq.read_schema(reference / "trials.parquet").metadata
    assert md[b"stereopose_mc.scenario"] == b"caseB"
    assert b"stereopose_mc.schema_version" in md


def test_existing_run_directory_is_not_overwritten(scenario, reference):
    before = (reference / "trials.parquet").read_bytes()
    r = spmc("run", scenario, "--out", reference, "--quiet")
    assert r.exit_code == 2
    assert "--overwrite" in r.output
    assert (reference / "trials.parquet").read_bytes() == before


def test_resume_with_an_edited_scenario_is_refused(scenario, tmp_path):
    out = tmp_path / "run"
    run_ok("run", scenario, "--out", out)
    cfg = out / "config.yaml"
    cfg.write_text(cfg.read_text().replace("seed: 2014", "seed: 2015"))
    r = spmc("run", "--resume", out, "--quiet")
    assert r.exit_code == 2
    assert "scenario differs" in r.output


def test_killed_run_resumes_to_the_same_bytes(tmp_path):
    scn = write_scenario(tmp_path / "s.yaml", trials=40, time=SHORT)
    reference = tmp_path / "uninterrupted"
    run_ok("run", scn, "--out", reference, "--jobs", 2, "--chunk-size", 20)
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "stereopose_mc.cli.main", "run", str(scn), "--out", str(out), "--chunk-size", "1",
           "--quiet", "--no-report"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline:
        if len(list((out / "chunks").glob("trials-*.parquet"))) >= 3 if (out / "chunks").is_dir() else False:
            break
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (out / "trials.parquet").exists(), "the run finished before it could be killed"
    done = len(list((out / "chunks").glob("trials-*.parquet")))
    assert 3 <= done < 40
    r = spmc("run", "--resume", out, "--quiet", "--no-report")
    assert r.exit_code == 0, r.output
    same_bytes(reference, out)
    assert not list((out / "chunks").glob(".*.tmp"))


def test_rerun_reproduces_a_trial(reference, tmp_path):
    r = spmc("rerun", reference, "--trial", 5, "--out", tmp_path / "t5.parquet")
    assert r.exit_code == 0, r.output
    assert "identical to trials.parquet" in r.output
    ts = pd.read_parquet(tmp_path / "t5.parquet")
    ref = pd.read_parquet(reference / "timeseries.parquet")
    ref = ref[ref["trial"] == 5].reset_index(drop=True)
    pd.testing.assert_frame_equal(ts.reset_index(drop=True), ref)


def test_the_manifest_records_the_blas_kernels_and_rerun_says_when_its_own_differ(reference, monkeypatch):
    import json

    from threadpoolctl import threadpool_info

    from stereopose_mc.mc import engine

    recorded = json.loads((reference / "manifest.json").read_text())["backend"]["blas"]
    archs = {i.get("architecture") for i in threadpool_info() if i["user_api"] == "blas"}
    assert recorded == engine.blas_kernels() and any(a in recorded for a in archs)  # e.g. "openblas Haswell"
    r = spmc("rerun", reference, "--trial", 5)
    assert r.exit_code == 0 and "BLAS kernels" not in r.output  # the same kernels: nothing to say
    monkeypatch.setattr(engine, "blas_kernels", lambda: "openblas OtherCPU")
    r = spmc("rerun", reference, "--trial", 5)
    assert r.exit_code == 0, r.output
    assert f"the run's BLAS kernels ({recorded}) are not this process's (openblas OtherCPU)" in r.output


def test_dask_local_cluster_equals_local_run(scenario, reference, tmp_path):
    pytest.importorskip("dask.distributed")
    out = tmp_path / "run"
    run_ok("run", scenario, "--out", out, "--jobs", 2, "--chunk-size", 3, "--backend", "dask")
    same_bytes(reference, out)


def test_ctrl_c_keeps_finished_chunks_and_says_how_to_resume(tmp_path):
    scn = write_scenario(tmp_path / "s.yaml", trials=200, time=SHORT)
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "stereopose_mc.cli.main", "run", str(scn), "--out", str(out), "--chunk-size", "2",
           "--no-report"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
    deadline = time.time() + 120
    while time.time() < deadline and not (out.is_dir() and list((out / "chunks").glob("trials-*.parquet"))):
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode == 130, err
    assert f"spmc run --resume {out}" in err
    assert list((out / "chunks").glob("trials-*.parquet"))
    assert not (out / "trials.parquet").exists()


def _first_chunk_slow(monkeypatch, seen=None, slow=0):
    """The chunk of trial ``slow`` finishes last (the threads' other chunks overtake it); ``seen``: (first
    trial, thread) per write."""
    import threading

    from stereopose_mc.mc import engine

    real_compute, real_write = engine.compute_chunk, engine._write_chunk

    def compute(scenario_json, trials, *args, **kwargs):
        if int(trials[0]) == slow:
            time.sleep(1.0)
        return real_compute(scenario_json, trials, *args, **kwargs)

    def write(chunk_dir, co, *args, **kwargs):
        if seen is not None:
            seen.append((int(co.trials[0]), threading.current_thread().name))
        return real_write(chunk_dir, co, *args, **kwargs)

    monkeypatch.setattr(engine, "compute_chunk", compute)
    monkeypatch.setattr(engine, "_write_chunk", write)


def test_chunks_finishing_out_of_order_merge_to_the_same_bytes(scenario, reference, tmp_path, monkeypatch):
    from stereopose_mc import api

    seen = []
    _first_chunk_slow(monkeypatch, seen)
    out = tmp_path / "run"
    api.run(scenario, out=out, jobs=2, chunk_size=2, backend="threading", kernels="compiled")
    same_bytes(reference, out)
    assert [f for f, _ in seen][-1] == 0 and sorted(f for f, _ in seen) == [0, 2, 4, 6]  # 0 waited for the others
    assert {name.split("_")[0] for _, name in seen} == {"spmc-chunk"}  # written by the threads that computed them
    assert not list(out.glob(".publish-*"))


def test_forked_workers_finishing_out_of_order_merge_to_the_same_bytes(scenario, reference, tmp_path, monkeypatch):
    """The default backend of the compiled kernels on Linux: the chunks computed and written in forked workers
    (the monkeypatched functions are theirs through the fork), merged in trial order by this process."""
    from stereopose_mc import api
    from stereopose_mc.mc import engine, forked

    if not forked.available():
        pytest.skip("forked workers: Linux only")
    _first_chunk_slow(monkeypatch, None)
    out = tmp_path / "run"
    api.run(scenario, out=out, jobs=2, chunk_size=2, kernels="compiled")
    same_bytes(reference, out)
    m = json.loads((out / "manifest.json").read_text())
    assert m["backend"]["backend"] == "auto" and m["backend"]["ran_as"] == "fork"
    assert engine.local_backend(engine.RunOptions(jobs=2), 4) == "fork"


def test_resume_merges_earlier_chunk_files_with_new_chunks(scenario, reference, tmp_path, monkeypatch):
    from stereopose_mc import api

    out = tmp_path / "run"
    api.run(scenario, out=out, jobs=2, chunk_size=2, backend="threading")
    for name in ("trials", "timing", "timeseries"):  # chunk 2-3 and 6-7 are to be recomputed
        for rng in ("0000002-0000003", "0000006-0000007"):
            (out / "chunks" / f"{name}-{rng}.parquet").unlink()
    seen = []
    _first_chunk_slow(monkeypatch, seen, slow=2)
    api.resume(out, chunk_size=1, backend="threading")  # (``seen`` is filled in this process)
    assert seen[-1][0] == 2 and sorted(f for f, _ in seen) == [2, 3, 6, 7]  # merged: 0-1 (file), 2, 3, 4-5 (file), 6, 7
    same_bytes(reference, out)


@pytest.mark.parametrize("backend", ["threading", "fork"])
def test_a_failing_chunk_leaves_no_merge_behind(scenario, tmp_path, monkeypatch, backend):
    from stereopose_mc import api
    from stereopose_mc.mc import engine, forked

    if backend == "fork" and not forked.available():
        pytest.skip("forked workers: Linux only")

    real = engine.compute_chunk

    def compute(scenario_json, trials, *args, **kwargs):
        if int(trials[0]) == 4:
            time.sleep(0.5)  # chunks 0-3 are merged by now
            raise RuntimeError("chunk 4-5 failed")
        return real(scenario_json, trials, *args, **kwargs)

    monkeypatch.setattr(engine, "compute_chunk", compute)
    out = tmp_path / "run"
    with pytest.raises(RuntimeError, match="chunk 4-5 failed"):
        api.run(scenario, out=out, jobs=2, chunk_size=2, backend=backend)
    assert not list(out.glob(".publish-*")) and not (out / "timeseries.parquet").exists()
    assert {p.name for p in (out / "chunks").glob("chunk-*.json")} >= {"chunk-0000000-0000001.json"}


@pytest.mark.parametrize("kind", ["trials", "timeseries"])
def test_a_chunk_file_changed_before_the_merge_is_refused_and_nothing_is_published(scenario, tmp_path, monkeypatch,
                                                                                    kind):  # fmt: skip
    """The final verification runs beside the merge (engine._verified_and_finalized): its verdict names the changed
    file, also where the merge itself failed on it (a truncated trials file), and nothing is published."""
    from stereopose_mc import api
    from stereopose_mc.api.errors import SpmcError
    from stereopose_mc.mc import engine

    real = engine._write_chunk

    def write(chunk_dir, co, *args, **kwargs):
        real(chunk_dir, co, *args, **kwargs)
        if int(co.trials[0]) == 2:  # after its sidecar: as if another process truncated the file
            f = chunk_dir / f"{kind}-0000002-0000003.parquet"
            f.write_bytes(f.read_bytes()[:100])

    monkeypatch.setattr(engine, "_write_chunk", write)
    out = tmp_path / "run"
    with pytest.raises(SpmcError, match=f"refusing to merge.*{kind}-0000002-0000003.parquet: truncated or corrupt"):
        api.run(scenario, out=out, jobs=2, chunk_size=2, backend="threading")
    assert not list(out.glob(".publish-*"))
    assert not any((out / n).exists() for n in ("trials.parquet", "timeseries.parquet", "percentiles.csv"))


def test_summary_time_series_merges_the_first_trials_for_any_chunking(tmp_path):
    import pyarrow.parquet as pq

    scn = write_scenario(tmp_path / "s.yaml", trials=104, time=SHORT)
    a, b = tmp_path / "a", tmp_path / "b"
    run_ok("run", scn, "--out", a, "--jobs", 1, "--chunk-size", 104, "--timeseries", "summary")
    run_ok("run", scn, "--out", b, "--jobs", 2, "--chunk-size", 5, "--timeseries", "summary")  # 100-103: none
    same_bytes(a, b)
    trials = pq.ParquetFile(b / "timeseries.parquet").read().column("trial").to_numpy()
    assert sorted(set(trials.tolist())) == list(range(100))  # SUMMARY_TRIALS
    assert len(trials) == 100 * 2 * 21  # 2 filters x 21 steps
    assert (b / "chunks" / "trials-0000100-0000103.parquet").is_file()
    assert not (b / "chunks" / "timeseries-0000100-0000103.parquet").exists()
