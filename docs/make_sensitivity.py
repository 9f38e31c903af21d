"""Regenerate the mission example's and the sweep's numbers in docs/sensitivity.md (issue 33).

    .venv/bin/python docs/make_sensitivity.py               # run the campaign, then rewrite the blocks
    .venv/bin/python docs/make_sensitivity.py --skip-runs   # rewrite them from runs/mission-debris/ as it is

The campaign is the doc's own command, ``spmc run configs/mission-debris.yaml --kernels
compiled --out runs/mission-debris`` (500 trials, the scenario's seed) followed by ``spmc
report runs/mission-debris`` (which writes ``sensitivity.csv``), run here through the
engine and the report; then the doc's sweep, ``spmc sweep configs/sweeps/baseline-range.yaml
--out runs/sweep-baseline-range`` (its ``percentiles.csv``). Only the text between ``<!-- sensitivity:<block>:begin -->`` and
``<!-- sensitivity:<block>:end -->`` in docs/sensitivity.md is replaced.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
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
SWEEP = ROOT / "runs" / "sweep-baseline-range"
SWEEP_CMD = ["sweep", "configs/sweeps/baseline-range.yaml", "--out", "runs/sweep-baseline-range", "--jobs"]
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
    shutil.rmtree(SWEEP, ignore_errors=True)  # a sweep resumes finished points; these are rerun
    spmc = Path(sys.executable).with_name("spmc")
    subprocess.run([str(spmc), *SWEEP_CMD, str(jobs), "--timeseries", "none", "--no-report", "-q"], cwd=ROOT,
                   check=True)  # fmt: skip


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


def sweep_tables() -> tuple[str, str]:
    """The sweep's IEKF median e_omega grid, and its reading (ranges, ratios, lost counts), from its percentiles."""
    meta = json.loads((SWEEP / "sweep.json").read_text())
    (bp, bs), (rp, rs) = ((a["path"], a["values"]) for a in meta["axes"])
    pc = pd.read_csv(SWEEP / "percentiles.csv")
    pc[["point", "label"]] = pc["filter"].str.rsplit("/", n=1, expand=True)
    med = pc[(pc["population"] == "converged") & (pc["percentile"] == 50)].set_index(["point", "label"])
    at = {(p["values"][bp], p["values"][rp]): p["name"] for p in meta["points"]}

    def get(b, r, label, col):
        return med.loc[(at[b, r], label), col]

    lines = ["| baseline \\ range | " + " | ".join(f"{r:g} m" for r in rs) + " |", "|" + "---|" * (len(rs) + 1)]
    lines += [f"| {b:g} m | " + " | ".join(f"{get(b, r, 'iekf', 'e_omega'):.2g}" for r in rs) + " |" for b in bs]
    ratio = {r: get(bs[0], r, "iekf", "e_omega") / get(bs[-1], r, "iekf", "e_omega") for r in rs}
    span = {c: [get(b, r, "iekf", c) for b in bs for r in rs] for c in ("e_rho", "e_k1", "e_k2")}
    lost = {(b, r, f): int(get(b, r, f, "lost")) for b in bs for r in rs for f in ("iekf", "ekf")}
    n = int(meta["trials"])

    def lost_range(f, r):
        v = [lost[b, r, f] for b in bs]
        return f"{min(v)}-{max(v)} of {n}" if min(v) != max(v) else f"{v[0]} of {n}"

    text = (f"The rate error falls with the baseline, most at long range (x{ratio[rs[-1]]:.2g} from {bs[0]:g} to "
            f"{bs[-1]:g} m at {rs[-1]:g} m, x{ratio[rs[0]]:.2g} at {rs[0]:g} m). The median position error "
            f"({min(span['e_rho']):.2g}-{max(span['e_rho']):.2g} m over the grid) and the inertia-ratio errors (k1 "
            f"{min(span['e_k1']):.2g}-{max(span['e_k1']):.2g}, k2 {min(span['e_k2']):.2g}-{max(span['e_k2']):.2g}) "
            f"move less. Lost trials per point: the EKF {lost_range('ekf', rs[0])} at {rs[0]:g} m and "
            f"{lost_range('ekf', rs[-1])} at {rs[-1]:g} m; the IEKF at most "
            f"{max(lost[b, r, 'iekf'] for b in bs for r in rs)} of {n}.")
    return "\n".join(lines), text


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=available_cores(), help="default: the cores available")
    ap.add_argument("--skip-runs", action="store_true")
    a = ap.parse_args(argv)
    if not a.skip_runs:
        run(a.jobs)
    t = pd.read_parquet(RUN / "trials.parquet")
    s = pd.read_csv(RUN / "sensitivity.csv")
    note = "<!-- generated by docs/make_sensitivity.py from runs/{}/; do not edit by hand -->\n"
    text = DOC.read_text(encoding="utf-8")
    grid, reading = sweep_tables()
    blocks = (("outcome", outcome(t)), ("drivers", drivers_table(s)), ("tumble", tumble_table(t)),
              ("sweep", grid), ("sweep-reading", reading))  # fmt: skip
    for block, body in blocks:
        src = SWEEP.name if block.startswith("sweep") else RUN.name
        text = splice(text, f"sensitivity:{block}", note.format(src) + body, DOC)
    DOC.write_text(text, encoding="utf-8")
    print(f"wrote {DOC}")


if __name__ == "__main__":
    main(sys.argv[1:])
