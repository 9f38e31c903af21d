"""``--kernels compiled``: whole trials agree with the numpy reference; threads, jobs and chunk sizes
give the same bytes (case B's filters in the aligned error state, their default, and in the full state)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from stereopose_mc.cli.main import app
from stereopose_mc.mc import engine

from scenarios import write_scenario

runner = CliRunner()
SHORT = {"dt_s": 1.0, "duration_s": 20.0, "error_window_start_s": 5.0}


def run_ok(*args):
    r = runner.invoke(app, [str(a) for a in args] + ["--quiet", "--no-report"])
    assert r.exit_code == 0, r.output
    return r


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    return write_scenario(tmp_path_factory.mktemp("scn") / "s.yaml", trials=8, time=SHORT)


@pytest.fixture(scope="module")
def compiled_ref(scenario, tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "run"
    run_ok("run", scenario, "--out", out, "--jobs", 1, "--chunk-size", 8, "--kernels", "compiled")
    return out


def same_bytes(a: Path, b: Path):
    for n in ("trials.parquet", "timeseries.parquet", "percentiles.csv"):
        assert (a / n).read_bytes() == (b / n).read_bytes(), n


@pytest.mark.parametrize("jobs,chunk,backend", [(2, 3, "auto"), (2, 5, "loky"), (1, 1, "auto")])
def test_compiled_same_bytes_for_any_jobs_chunk_and_backend(scenario, compiled_ref, tmp_path, jobs, chunk, backend):
    out = tmp_path / "run"
    run_ok("run", scenario, "--out", out, "--jobs", jobs, "--chunk-size", chunk, "--kernels", "compiled",
           "--backend", backend)  # fmt: skip
    same_bytes(compiled_ref, out)


def test_compiled_full_state_same_bytes_for_any_jobs_and_chunk(tmp_path):
    full = [{"type": "iekf", "error_state": "full"}, {"type": "ekf", "error_state": "full"}]
    scn = write_scenario(tmp_path / "full.yaml", trials=8, time=SHORT, filters=full)
    a, b = tmp_path / "a", tmp_path / "b"
    run_ok("run", scn, "--out", a, "--jobs", 1, "--chunk-size", 8, "--kernels", "compiled")
    run_ok("run", scn, "--out", b, "--jobs", 2, "--chunk-size", 3, "--kernels", "compiled")
    same_bytes(a, b)


def test_auto_backend_picks_forked_workers_for_compiled_and_inline_for_one_chunk(monkeypatch):
    from stereopose_mc.mc import forked

    opts = engine.RunOptions(jobs=2, backend="auto", kernels="compiled")
    assert engine.local_backend(opts, 4) == ("fork" if sys.platform.startswith("linux") else "threading")
    monkeypatch.setattr(forked, "available", lambda: False)  # macOS, Windows: threads
    assert engine.local_backend(opts, 4) == "threading"
    with pytest.raises(engine.RunError, match="--backend fork: worker processes are forked on Linux only"):
        engine.local_backend(engine.RunOptions(jobs=2, backend="fork"), 4)
    monkeypatch.undo()
    assert engine.local_backend(opts, 1) == "inline"
    assert engine.local_backend(engine.RunOptions(jobs=2, backend="auto", kernels="numpy"), 4) == "loky"
    assert engine.local_backend(opts, 4, images=True) == "loky"  # the tracker holds the GIL
    assert engine.local_backend(engine.RunOptions(jobs=1, backend="loky"), 4) == "inline"


def test_backend_fork_where_it_is_not_offered_is_one_line_exit_2_and_writes_nothing(scenario, tmp_path, monkeypatch):
    from stereopose_mc.mc import forked

    monkeypatch.setattr(forked, "available", lambda: False)
    out = tmp_path / "x"
    r = runner.invoke(app, ["run", str(scenario), "--out", str(out), "--backend", "fork", "--quiet"])
    assert r.exit_code == 2 and "--backend fork: worker processes are forked on Linux only" in r.output
    assert len(r.output.strip().splitlines()) == 1 and "Traceback" not in r.output
    assert not out.exists() and not list(tmp_path.glob(".x*"))


def test_auto_chunk_size_compiled_splits_over_jobs_but_keeps_small_runs_in_one_chunk():
    c = engine.RunOptions(jobs=2, kernels="compiled")
    sizes = {n: engine.auto_chunk_size(c, n) for n in (1, 2, 10, 40, 63, 64, 100, 1000)}
    assert sizes == {1: 1, 2: 2, 10: 10, 40: 32, 63: 32, 64: 32, 100: 50, 1000: 250}
    assert engine.auto_chunk_size(engine.RunOptions(jobs=2, kernels="numpy"), 2) == 50
    assert engine.auto_chunk_size(engine.RunOptions(jobs=1, kernels="compiled"), 100) == 100


def test_a_larger_state_splits_fewer_trials_over_the_jobs():
    """``min_chunk``: 32 trials at case B's n = 30, by (30 / n)^2 for larger states, at least 2 (by hand:
    32 (30 / 87)^2 = 3.8 -> 4 for configs/mission-realistic.yaml's n = 87; 32 (30 / 45)^2 = 14.2 -> 15)."""
    assert [engine.min_chunk(n) for n in (30, 45, 87, 159, 10_000)] == [32, 15, 4, 2, 2]
    c = engine.RunOptions(jobs=2, kernels="compiled")
    sizes = {t: engine.auto_chunk_size(c, t, 87) for t in (1, 3, 4, 7, 30, 1000)}
    assert sizes == {1: 1, 3: 3, 4: 4, 7: 4, 30: 15, 1000: 250}
    assert engine.auto_chunk_size(c, 30, 30) == 30  # case B: one chunk, inline


def test_a_small_compiled_run_runs_inline(scenario, compiled_ref, tmp_path):
    import json

    out = tmp_path / "run"
    run_ok("run", scenario, "--out", out, "--jobs", 2, "--kernels", "compiled")  # 8 trials: one chunk
    m = json.loads((out / "manifest.json").read_text())
    assert m["backend"]["ran_as"] == "inline" and len(m["chunks"]) == 1
    same_bytes(compiled_ref, out)


def test_bad_kernels_is_one_line_exit_2(scenario, tmp_path):
    r = runner.invoke(app, ["run", str(scenario), "--out", str(tmp_path / "x"), "--kernels", "fortran", "--quiet"])
    assert r.exit_code == 2 and "--kernels" in r.output
    assert not (tmp_path / "x").exists()


def test_resume_keeps_the_runs_kernels(scenario, compiled_ref, tmp_path):
    import json

    out = tmp_path / "run"
    run_ok("run", scenario, "--out", out, "--trials", 3, "--kernels", "compiled")
    run_ok("run", "--resume", out, "--trials", 8)  # no --kernels: the run's own
    assert json.loads((out / "manifest.json").read_text())["backend"]["kernels"] == "compiled"
    same_bytes(compiled_ref, out)
