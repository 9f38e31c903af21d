"""Regenerate the mission example's numbers in docs/sensitivity.md (issue 33).

    .venv/bin/python docs/make_sensitivity.py               # run the campaign, then rewrite the blocks
    .venv/bin/python docs/make_sensitivity.py --skip-runs   # rewrite them from runs/mission-debris/ as it is

The campaign is the doc's own command, ``spmc run configs/mission-debris.yaml --kernels
compiled --out runs/mission-debris`` (500 trials, the scenario's seed) followed by ``spmc
report runs/mission-debris`` (which writes ``sensitivity.csv``), run here through the
engine and the report. Only the text between ``<!-- sensitivity:<block>:begin -->`` and
``<!-- sensitivity:<block>:end -->`` in docs/sensitivity.md is replaced.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from docgen import reason_kind, splice

from stereopose_mc.config import load_scenario
from stereopose_mc.mc import engine
from stereopose_mc.mc.cores import available_cores
from stereopose_mc.rundir.percentiles import percentile_table

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "mission-debris.yaml"
RUN = ROOT / "runs" / "mission-debris"
DOC = ROOT / "docs" / "sensitivity.md"
RATE = "|truth_initial_state.omega_degps|"
BINS = (0.0, 1.0, 2.0, 3.0)  # tumble rate, deg/s (the scenario draws it uniform in 0.1-3)
METRICS = ("e_k1", "e_k2", "e_rho", "e_rho_dot", "e_omega", "e_theta", "diverged")
NAMES = {RATE: "tumble rate `\\|omega\\|`", "truth_initial_state.rho_m[1]": "along-track range `rho_m[1]`",
         "target.inertia_kgm2[0]": "I_x", "target.inertia_kgm2[1]": "I_y", "target.inertia_kgm2[2]": "I_z"}  # fmt: skip


def run(jobs: int) -> None:
    from stereopose_mc.outputs.report import build_run_report

    engine.run(load_scenario(CONFIG), RUN, engine.RunOptions(jobs=jobs, overwrite=True, command=[
        "spmc", "run", "configs/mission-debris.yaml", "--kernels", "compiled", "--out", "runs/mission-debris"]))  # fmt: skip
    build_run_report(RUN)


def name(p: str) -> str:
    return NAMES.get(p, f"`{p}`")


def outcome(t: pd.DataFrame) -> str:
    out = []
    for label, g in t.groupby("filter", sort=False):
        lost = g["lost"].to_numpy(bool)
        kinds = g.loc[lost, "lost_reason"].map(reason_kind)
        ok = g[~lost]
        pt = percentile_table(g, [50, 90])
        pt = pt[pt["population"] == "converged"].set_index("percentile")
        q = {e: (pt.loc[50.0, e], pt.loc[90.0, e]) for e in ("e_rho", "e_omega", "e_theta", "e_k1")}
        out.append(f"{label.upper()}: loses {lost.sum()} of {len(g)} trials ("
                   + ", ".join(f"{v} {k}" for k, v in kinds.value_counts().items())
                   + f"), {int(g['inconsistent'].sum())} flagged inconsistent, {int(g['invalid'].sum())} invalid draws; "
                   f"percentiles 50 / 90 % over the {len(ok)} trials not lost: "
                   + ", ".join(f"{e} {a:.2g} / {b:.2g}" for e, (a, b) in q.items()) + ".")  # fmt: skip
    return "\n".join(f"- {line}" for line in out)


def drivers_table(s: pd.DataFrame, label: str = "iekf") -> str:
    g = s[s["filter"] == label].assign(a=lambda d: d["value"].abs()).sort_values("a", ascending=False)
    lines = ["| metric | strongest driver | statistic [95 % CI] | next two |", "|---|---|---|---|"]

    def stat(r) -> str:
        ci = f" [{r.ci_low:.2f}, {r.ci_high:.2f}]" if np.isfinite(r.ci_low) else ""
        sig = "significant" if r.significant else f"p = {r.p:.2g}, not significant"
        return f"{'r' if r.statistic == 'rank-biserial' else 'rho'} = {r.value:+.2f}{ci}, {sig}"

    for m in METRICS:
        top = list(g[g["metric"] == m].head(3).itertuples())
        if not top:
            continue
        nxt = "; ".join(f"{name(r.parameter)} {r.value:+.2f}{' (significant)' if r.significant else ''}" for r in top[1:])
        lines.append(f"| {'lost' if m == 'diverged' else m} | {name(top[0].parameter)} | {stat(top[0])} | {nxt} |")
    return "\n".join(lines)


def tumble_table(t: pd.DataFrame) -> str:
    labels = list(pd.unique(t["filter"]))
    head = ["tumble rate (deg/s)", "trials", *(f"{f.upper()} lost" for f in labels),
            "IEKF median k1, k2, rho (m) (not lost)"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        cells = []
        for f in labels:
            g = t[(t["filter"] == f) & (t[RATE] >= lo) & (t[RATE] < hi)]
            cells.append(f"{int(g['lost'].sum())} ({100 * g['lost'].mean():.0f} %)")
        i = t[(t["filter"] == "iekf") & (t[RATE] >= lo) & (t[RATE] < hi) & ~t["lost"]]
        med = ", ".join(f"{np.median(i[e]):.2g}" for e in ("e_k1", "e_k2", "e_rho"))
        lines.append(f"| {lo:g}-{hi:g} | {len(g)} | " + " | ".join(cells) + f" | {med} |")
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=available_cores(), help="default: the cores available")
    ap.add_argument("--skip-runs", action="store_true")
    a = ap.parse_args(argv)
    if not a.skip_runs:
        run(a.jobs)
    t = pd.read_parquet(RUN / "trials.parquet")
    s = pd.read_csv(RUN / "sensitivity.csv")
    note = "<!-- generated by docs/make_sensitivity.py from runs/mission-debris/; do not edit by hand -->\n"
    text = DOC.read_text(encoding="utf-8")
    for block, body in (("outcome", outcome(t)), ("drivers", drivers_table(s)), ("tumble", tumble_table(t))):
        text = splice(text, f"sensitivity:{block}", note + body, DOC)
    DOC.write_text(text, encoding="utf-8")
    print(f"wrote {DOC}")


if __name__ == "__main__":
    main(sys.argv[1:])
