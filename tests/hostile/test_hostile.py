"""Compact versions of the hostile reproductions of issue 34: each stays fixed.

Runs are small (case B, a few trials of 12 s: ``quick_scenario``); crashes are injected by
monkeypatching the rename at the named moment. Every bad input: one line, exit 2, nothing
half-written, no traceback.
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import pytest

from cli_helpers import one_error_line, run_ok, spmc


@pytest.fixture(scope="module")
def run6(quick_scenario, tmp_path_factory):
    out = tmp_path_factory.mktemp("r") / "run"
    run_ok("run", quick_scenario, "--out", out, "--chunk-size", 3)
    return out


def _tree(d: Path) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in d.rglob("*"))


# 1. --overwrite replaces only this tool's directories
@pytest.mark.parametrize("command", ["run", "simulate"])
def test_overwrite_refuses_a_foreign_directory(command, quick_scenario, tmp_path):
    d = tmp_path / "d"
    (d / "sub").mkdir(parents=True)
    (d / "thesis.tex").write_text("x")
    (d / "sub" / "fig.png").write_text("y")
    extra = ("--trials", 2, "--quiet", "--no-report") if command == "run" else ()
    r = spmc(command, quick_scenario, "--out", d, "--overwrite", *extra)
    one_error_line(r, str(d), "not a run, sweep or simulation directory", "--overwrite")
    assert _tree(d) == ["sub", "sub/fig.png", "thesis.tex"]
    assert [p.name for p in tmp_path.iterdir()] == ["d"]  # no staging sibling left behind


def test_overwrite_refuses_a_manifest_of_another_tool(quick_scenario, tmp_path):
    d = tmp_path / "d"
    d.mkdir()
    (d / "manifest.json").write_text(json.dumps({"kind": "run", "package": "other"}))
    one_error_line(spmc("run", quick_scenario, "--out", d, "--overwrite", "--trials", 2, "--quiet"),
                   "not a run, sweep or simulation directory")  # fmt: skip
    assert _tree(d) == ["manifest.json"]


def test_overwrite_replaces_a_run_directory(run6, quick_scenario, tmp_path):
    import shutil

    d = tmp_path / "run"
    shutil.copytree(run6, d)
    run_ok("run", quick_scenario, "--out", d, "--overwrite", "--trials", 2)
    assert json.loads((d / "manifest.json").read_text())["trials"] == 2


# 2. never write over a non-regular file
def test_rerun_out_refuses_a_fifo(run6, tmp_path):
    n = tmp_path / "n"
    os.mkfifo(n)
    one_error_line(spmc("rerun", run6, "--trial", 0, "--out", n), str(n), "not a regular file")
    assert stat.S_ISFIFO(os.lstat(n).st_mode)
    assert [p.name for p in tmp_path.iterdir()] == ["n"]


def test_atomic_write_refuses_a_non_regular_file(tmp_path):
    from stereopose_mc.rundir import store

    n = tmp_path / "n"
    os.mkfifo(n)
    with pytest.raises(OSError, match="not a regular file"):
        store.atomic_write_text(n, "x")
    with pytest.raises(OSError, match="not a regular file"):
        store.write_parquet(n, {"a": __import__("numpy").arange(3)})
    assert stat.S_ISFIFO(os.lstat(n).st_mode) and [p.name for p in tmp_path.iterdir()] == ["n"]
