"""The report's section on the tracker and its truth audit (``tracks.parquet`` of an images run, docs/images.md).

Shown only when the run directory has ``tracks.parquet`` (``measurements.source: images``, or a ``tracks`` file that
carries the audit's columns): per run, the tracks and their lifetimes, the live tracks per step, the share of clean
tracks (never off their surface or hidden, born on the body), and the tracked positions' errors against the true
projection of each track's body point, after the detection step (where the audit defines that point, so the error
is 0 by construction).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from .html import html_table

if TYPE_CHECKING:
    from .report import RunData

AUDIT = ("err_r_px", "clean", "lifetime", "jumped")


def audit_rows(tracks: pd.DataFrame) -> list[list[str]]:
    """The audit's numbers as table rows ``[quantity, value]``."""
    per_track = tracks.groupby(["trial", "track_id"], sort=False).agg(life=("step", "size"), clean=("clean", "first"),
                                                                      jumped=("jumped", "first"))  # fmt: skip
    live = tracks.groupby(["trial", "step"], sort=False).size()
    e = tracks.loc[(tracks["age"].to_numpy() > 0) & tracks["clean"].to_numpy(), "err_r_px"].to_numpy(float)
    e = e[np.isfinite(e)]
    q = (lambda p: f"{float(np.quantile(e, p)):.3f}") if e.size else (lambda p: "-")
    return [
        ["trials", str(tracks["trial"].nunique())],
        ["tracks", str(len(per_track))],
        ["live tracks per step: median (min - max)", f"{live.median():g} ({live.min()} - {live.max()})"],
        ["track lifetime [steps]: median (max)", f"{per_track['life'].median():g} ({per_track['life'].max()})"],
        ["clean tracks", f"{int(per_track['clean'].sum())} ({per_track['clean'].mean():.1%})"],
        ["tracks that jumped (off their surface or hidden)", str(int(per_track["jumped"].sum()))],
        [f"right-image error of clean tracks after detection [px]: median / p90 / p99 ({e.size} rows)",
         f"{q(0.5)} / {q(0.9)} / {q(0.99)}"],
    ]  # fmt: skip


def section(data: RunData) -> list[str]:
    """HTML of the section (empty without an audited ``tracks.parquet``)."""
    path = data.path / "tracks.parquet"
    if not path.is_file():
        return []
    tracks = pd.read_parquet(path)
    if not set(AUDIT) | {"age", "track_id", "step", "trial"} <= set(tracks.columns) or tracks.empty:
        return []
    return ["<h2>Tracker and its truth audit</h2>",
            "<p>The tracks that measured this run (<code>tracks.parquet</code>; docs/images.md, Truth audit).</p>",
            html_table(["quantity", "value"], audit_rows(tracks), left=1)]
