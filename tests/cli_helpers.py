"""Helpers for tests that drive the ``spmc`` CLI in-process."""

from __future__ import annotations

from typer.testing import CliRunner

from stereopose_mc.cli.main import app

SHORT = {"dt_s": 1.0, "duration_s": 12.0, "error_window_start_s": 5.0}  # 13 steps: quick runs


def spmc(*args):
    """Invoke ``spmc ARGS`` (stdout and stderr together in ``.output``)."""
    return CliRunner().invoke(app, [str(a) for a in args])


def run_ok(*args):
    """``spmc ARGS --quiet --no-report``, asserting exit 0."""
    r = spmc(*args, "--quiet", "--no-report")
    assert r.exit_code == 0, r.output
    return r


def one_error_line(r, *needles: str) -> str:
    """Assert exit 2 with exactly one ``error: ...`` line containing every needle; return it."""
    assert r.exit_code == 2, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.output
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]
