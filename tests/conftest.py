"""Shared fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest
from scenarios import write_scenario


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config) -> int:
    """``make test``'s ``-n auto``: one worker per core available to the process, as ``--jobs``' default counts
    them (``mc.cores.available_cores``: the affinity mask capped by a cgroup CPU quota; xdist's own count reads the
    affinity mask only)."""
    from stereopose_mc.mc.cores import available_cores

    return available_cores()


@pytest.fixture(scope="session", autouse=True)
def _session_truth_cache(tmp_path_factory):
    """The truth cache (sim/truth_cache.py) of this test session in its own directory, never ~/.cache:
    the suite's runs fill it and use it (subprocesses inherit the variable)."""
    mp = pytest.MonkeyPatch()
    mp.setenv("SPMC_CACHE_DIR", str(tmp_path_factory.mktemp("spmc-cache")))
    yield
    mp.undo()


@pytest.fixture
def small_caseB(tmp_path) -> Path:
    """Case B cut to 6 trials of 20 s (window from 5 s)."""
    return write_scenario(
        tmp_path / "small.yaml", trials=6, time={"dt_s": 1.0, "duration_s": 20.0, "error_window_start_s": 5.0}
    )


@pytest.fixture(scope="module")
def quick_scenario(tmp_path_factory) -> Path:
    """Case B cut to 6 trials of 12 s (13 steps, window from 5 s), shared by a test module."""
    from cli_helpers import SHORT

    return write_scenario(tmp_path_factory.mktemp("scn") / "quick.yaml", trials=6, time=SHORT)
