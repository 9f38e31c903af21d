"""The ``spmc`` process ends without the interpreter's teardown (``cli.main.exit_now``): same exit codes,
complete output, files written."""

from __future__ import annotations

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
