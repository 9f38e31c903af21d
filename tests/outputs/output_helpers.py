"""Helpers shared by the output tests."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from typer.testing import CliRunner

import stereopose_mc.cli.report_cmds  # noqa: F401  (registers 'report' and 'compare')
from stereopose_mc.cli.main import app

SHORT = {"dt_s": 1.0, "duration_s": 20.0, "error_window_start_s": 5.0}
RUN_FILES = ("config.yaml", "manifest.json", "trials.parquet", "timeseries.parquet", "timing.parquet",
             "percentiles.csv", "percentiles.md", "percentiles.parquet")  # fmt: skip


def spmc(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def copy_run(src: Path, dst: Path, drop: tuple[str, ...] = ()) -> Path:
    """Copy a run's table files (not its figures or report) to ``dst``, leaving out ``drop``.

    The copy stands for a run directory assembled or edited by hand: its manifest has no
    publication record (``rundir/publish.py``), so its tables may be edited.
    """
    dst.mkdir(parents=True)
    for n in RUN_FILES:
        if n not in drop and (src / n).exists():
            shutil.copy2(src / n, dst / n)
    m = dst / "manifest.json"
    if m.is_file() and "manifest.json" not in drop:
        d = json.loads(m.read_text())
        if isinstance(d, dict):
            d.pop("published", None)
            m.write_text(json.dumps(d))
    return dst
