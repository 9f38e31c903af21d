"""A tiny run directory shared by the output tests (case B, 6 trials of 20 s, both filters)."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from stereopose_mc.cli.main import app

from scenarios import write_scenario


@pytest.fixture(scope="session")
def run_dir(tmp_path_factory) -> Path:
    """``spmc run`` with its report (the default) on case B cut to 6 trials of 20 s, named ``caseB-small``."""
    d = tmp_path_factory.mktemp("outputs")
    short = {"dt_s": 1.0, "duration_s": 20.0, "error_window_start_s": 5.0}
    scn = write_scenario(d / "caseB-small.yaml", name="caseB-small", trials=6, time=short)
    out = d / "run"
    r = CliRunner().invoke(app, ["run", str(scn), "--out", str(out), "--jobs", "1", "--quiet"])
    assert r.exit_code == 0, r.output
    return out
