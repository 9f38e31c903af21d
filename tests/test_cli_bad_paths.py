"""Every bad path is one line and exit 2, and no option is silently ignored (issue 13, items 3-4)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import psutil
import pytest
import yaml

from stereopose_mc.config import budget
from stereopose_mc.mc import engine

from cli_helpers import SHORT, one_error_line, run_ok, spmc
from scenarios import scenario_dict, write_scenario


@pytest.fixture(scope="module")
def run6(quick_scenario, tmp_path_factory):
    out = tmp_path_factory.mktemp("r") / "run"
    run_ok("run", quick_scenario, "--out", out, "--chunk-size", 3)
    return out


def test_rerun_out_onto_a_directory(run6, tmp_path):
    one_error_line(spmc("rerun", run6, "--trial", 1, "--out", tmp_path), "is a directory", "t1.parquet")


def test_dynamics_out_onto_a_file(quick_scenario, tmp_path):
    f = tmp_path / "f.txt"
    f.write_text("keep")
    one_error_line(spmc("dynamics", quick_scenario, "--out", f), str(f), "not a directory")
    assert f.read_text() == "keep"


def test_simulate_out_under_a_file(quick_scenario, tmp_path):
    f = tmp_path / "f.txt"
    f.write_text("keep")
    one_error_line(spmc("simulate", quick_scenario, "--out", f / "sim"), str(f / "sim"))


def test_scheduler_needs_dask(quick_scenario, tmp_path):
    one_error_line(spmc("run", quick_scenario, "--backend", "loky", "--scheduler", "tcp://127.0.0.1:1",
                        "--out", tmp_path / "x"),
                   "--scheduler", "needs --backend dask")  # fmt: skip
    assert not (tmp_path / "x").exists()


def test_scheduler_implies_dask_and_a_wrong_address_is_one_line(quick_scenario, tmp_path, monkeypatch):
    pytest.importorskip("dask.distributed")
    monkeypatch.setattr(engine, "DASK_CONNECT_TIMEOUT_S", 1)
    r = spmc("run", quick_scenario, "--scheduler", "tcp://127.0.0.1:9", "--out", tmp_path / "x",
             "--quiet", "--no-report")
    one_error_line(r, "--scheduler tcp://127.0.0.1:9: cannot connect to a Dask scheduler")
    assert not (tmp_path / "x").exists()


def test_a_trial_count_that_cannot_fit_is_refused_with_the_number(tmp_path):
    d = scenario_dict(trials=10**14)
    f = tmp_path / "big.yaml"
    f.write_text(yaml.safe_dump(d, sort_keys=False))
    line = one_error_line(spmc("validate", f), f"{f}:", "trials: 100000000000000 trials x 2 filter(s) need about")
    assert "PiB" in line and "of at most" in line
    r = spmc("run", write_scenario(tmp_path / "s.yaml", trials=4), "--trials", 10**14, "--out", tmp_path / "o")
    one_error_line(r, "--trials: 100000000000000 trials")
    assert not (tmp_path / "o").exists()
    # the estimate itself: rows x bytes, against the memory given
    assert budget.memory_problem(1000, 2, memory=10**9) is None
    msg = budget.memory_problem(10**6, 2, memory=10**9)  # 1e6 x (2 x 300 x 3 + 24) B = 1.824e9 B
    assert "need about 1.7 GiB" in msg and "954 MiB" in msg and "at most 548245 trials" in msg


def test_non_utf8_scenario_names_line_and_byte(tmp_path):
    f = tmp_path / "latin1.yaml"
    f.write_bytes("name: x\n# caf\u00e9 au lait\ntrials: 3\n".encode("latin-1"))
    one_error_line(spmc("validate", f), f"{f}:2:", "byte 0xe9 at column 6")


def test_duplicate_feature_points_are_rejected(tmp_path):
    d = scenario_dict()
    pts = d["target"]["feature_points_m"]
    pts.append(list(pts[1]))
    f = tmp_path / "dup.yaml"
    f.write_text(yaml.safe_dump(d, sort_keys=False))
    one_error_line(spmc("validate", f), f"target.feature_points_m.{len(pts) - 1}", "duplicates point 1")


@pytest.mark.parametrize("args,needle", [
    (("--seed", 9), "started with seed 2014; --seed 9"),
    (("--trials", 2), "has 6 trials; --trials 2 cannot shrink it"),
    (("--overwrite",), "--resume and --overwrite conflict"),
    (("--out", "elsewhere"), "--out and --resume conflict"),
    (("--timeseries", "none"), "started with --timeseries full"),
])  # fmt: skip
def test_resume_options_that_conflict_are_named(run6, args, needle):
    one_error_line(spmc("run", "--resume", run6, *args, "--quiet", "--no-report"), needle)


def test_resume_with_more_trials_extends_the_run_and_says_so(quick_scenario, run6, tmp_path):
    import shutil

    out = tmp_path / "ext"
    shutil.copytree(run6, out)
    r = spmc("run", "--resume", out, "--trials", 8, "--quiet", "--no-report")
    assert r.exit_code == 0 and "extending the run from 6 to 8 trials" in r.output, r.output
    fresh = tmp_path / "fresh"
    run_ok("run", quick_scenario, "--trials", 8, "--out", fresh)
    for n in ("trials.parquet", "timeseries.parquet", "percentiles.csv"):
        assert (out / n).read_bytes() == (fresh / n).read_bytes(), n


def test_progress_on_resume_counts_finished_divergences_per_filter(tmp_path):
    """Every trial is lost (a NIS window test no filter passes): the first progress call of a resume already counts
    the finished chunk's lost trials, filter by filter."""
    f = write_scenario(tmp_path / "div.yaml", trials=4, time=SHORT,
                       divergence={"nis_ratio": 1e-9, "nis_window_steps": 1, "nis_start_s": 0.0})  # fmt: skip
    from stereopose_mc.config import load_scenario

    s = load_scenario(f)
    out = tmp_path / "run"
    engine.run(s, out, engine.RunOptions(chunk_size=2, command=["test"]))
    for p in (out / "chunks").glob("*-0000002-0000003.*"):
        p.unlink()
    calls = []
    engine.run(s, out, engine.RunOptions(chunk_size=2, resume=True, command=["test"]),
               lambda done, total, div: calls.append((done, total, div)))  # fmt: skip
    labels = [fl.label for fl in s.filters]
    assert calls[0] == (2, 4, {lab: 2 for lab in labels})
    assert calls[-1] == (4, 4, {lab: 4 for lab in labels})


def _cmdline(p: psutil.Process) -> str:
    """A process's command line, or '' for one that exited meanwhile (a zombie or gone)."""
    try:
        return " ".join(p.cmdline())
    except psutil.Error:
        return ""


def test_workers_die_with_their_parent(tmp_path):
    """SIGKILL the driver of a --jobs 2 run: its loky workers exit within seconds, not minutes."""
    f = write_scenario(tmp_path / "s.yaml", trials=40, time={"dt_s": 1.0, "duration_s": 100.0})
    cmd = [sys.executable, "-m", "stereopose_mc.cli.main", "run", str(f), "--out", str(tmp_path / "run"),
           "--jobs", "2", "--chunk-size", "20", "--quiet", "--no-report", "--kernels", "numpy"]  # fmt: skip (loky)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers: list[psutil.Process] = []
    try:
        deadline = time.time() + 60
        while time.time() < deadline and len(workers) < 2:
            time.sleep(0.2)
            workers = [c for c in psutil.Process(proc.pid).children(recursive=True) if "loky" in _cmdline(c)]
        assert len(workers) >= 2, "no loky workers started"
        time.sleep(1.0)  # let them take their chunks
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        _, alive = psutil.wait_procs(workers, timeout=10)
        assert not alive, f"{len(alive)} worker(s) outlived their parent"
    finally:
        if proc.poll() is None:
            proc.kill()
        for w in workers:  # never leave our own orphans behind, even when the test fails
            if w.is_running():
                w.kill()
