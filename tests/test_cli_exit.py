"""The ``spmc`` process ends without the interpreter's teardown (``cli.main.exit_now``): same exit codes,
complete output, files written."""

from __future__ import annotations

import os
import subprocess
import sys

from cli_helpers import SHORT

from scenarios import write_scenario

SPMC = [sys.executable, "-m", "stereopose_mc.cli.main"]


def spmc(*args, **kw):
    return subprocess.run(SPMC + [str(a) for a in args], capture_output=True, text=True, timeout=300, **kw)


def test_help_and_usage_errors_keep_their_exit_codes():
    r = spmc("--help")
    assert r.returncode == 0 and "run" in r.stdout and r.stdout.rstrip().endswith("╯")
    r = spmc("no-such-command")
    assert r.returncode == 2 and "No such command" in r.stderr


def test_a_run_exits_0_with_its_summary_and_files(tmp_path):
    scn = write_scenario(tmp_path / "s.yaml", trials=2, time=SHORT)
    out = tmp_path / "run"
    r = spmc("run", scn, "--out", out, "--no-report")
    assert r.returncode == 0, r.stderr
    assert r.stdout.rstrip().endswith(f"-> {out}")  # stdout flushed before the process ended
    for name in ("trials.parquet", "timeseries.parquet", "percentiles.csv", "manifest.json"):
        assert (out / name).is_file()


def test_a_bad_scenario_is_exit_2_with_its_error_line(tmp_path):
    r = spmc("run", tmp_path / "missing.yaml", "--out", tmp_path / "run", "--quiet")
    assert r.returncode == 2 and r.stderr.startswith("error: ")
    assert not (tmp_path / "run").exists()


def test_openblas_idle_threads_sleep_at_once_unless_the_user_says_otherwise():
    """``spmc`` sets ``OPENBLAS_THREAD_TIMEOUT=4`` (OpenBLAS's idle pool threads sleep after 2^4 cycles instead of
    spinning ~0.1 s: BLAS runs single-threaded in the chunks) before numpy loads OpenBLAS, which reads it then; a
    value in the environment is kept."""
    from stereopose_mc.cli.main import BLAS_THREAD_TIMEOUT

    probe = ("import os, sys\nfrom stereopose_mc.cli import main as m\n"
             "m.app = lambda: print(os.environ.get('OPENBLAS_THREAD_TIMEOUT'), 'numpy' in sys.modules)\nm.main()\n")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_THREAD_TIMEOUT"}
    for given, want in ((None, BLAS_THREAD_TIMEOUT), ("9", "9")):
        e = env if given is None else {**env, "OPENBLAS_THREAD_TIMEOUT": given}
        r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, env=e)
        assert r.returncode == 0, r.stderr
        assert r.stdout.split() == [want, "False"]  # (numpy not loaded yet: OpenBLAS reads it as it loads)
    assert BLAS_THREAD_TIMEOUT == "4"
