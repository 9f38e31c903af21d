"""The example notebook (docs/examples/first-campaign.py, jupytext py:percent) runs, cell by cell, on a few short trials."""

from __future__ import annotations

from pathlib import Path

import jupytext
import matplotlib
import pytest

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOK = ROOT / "docs" / "examples" / "first-campaign.py"


def test_first_campaign_runs_as_a_notebook(tmp_path, monkeypatch):
    nb = jupytext.read(NOTEBOOK)
    kinds = [c.cell_type for c in nb.cells]
    assert kinds.count("markdown") >= 4 and kinds.count("code") >= 5
    matplotlib.use("Agg")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    monkeypatch.setenv("SPMC_EXAMPLE_TRIALS", "4")
    monkeypatch.setenv("SPMC_EXAMPLE_DURATION_S", "12")
    ns: dict = {"__name__": "__main__"}
    for i, cell in enumerate(c for c in nb.cells if c.cell_type == "code"):
        try:
            exec(compile(cell.source, f"{NOTEBOOK.name} cell {i}", "exec"), ns)
        except Exception as exc:  # name the cell that broke
            pytest.fail(f"code cell {i} raised {type(exc).__name__}: {exc}")
    assert ns["run"].n_trials == 4 and ns["again"].identical
    assert (tmp_path / "runs" / "first-campaign" / "export" / "first-campaign.mat").is_file()
    import matplotlib.pyplot as plt

    plt.close("all")
