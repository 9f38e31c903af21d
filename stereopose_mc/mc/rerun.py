"""Rerun one trial of a run exactly, from the run's scenario and the trial's seed."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ..rundir import publish, store, tables
from . import engine


class RerunError(Exception):
    pass


@dataclass
class RerunResult:
    trials: pd.DataFrame
    identical: bool
    lines: list[str] = field(default_factory=list)


def rerun_trial(run_dir: Path, trial: int, out: Path | None = None) -> RerunResult:
    """Recompute trial ``trial`` alone; compare with the run's ``trials.parquet`` row(s).

    An incomplete or inconsistent run directory (``rundir/publish.py``) is refused.
    """
    bad = publish.dir_problems(Path(run_dir))
    if bad:
        raise RerunError(bad[0])
    try:
        scn = engine.load_run_scenario(run_dir)
        kernels = engine.recorded_kernels(run_dir)
    except (engine.RunError, ValueError) as exc:
        raise RerunError(str(exc)) from None
    if out is not None and Path(out).is_dir():
        raise RerunError(f"--out {out} is a directory: give a file name, e.g. {Path(out) / f't{trial}.parquet'}")
    if out is not None:
        try:
            store.refuse_non_regular(Path(out))
        except OSError as exc:
            raise RerunError(f"--out {out}: {exc.strerror}") from None
    if trial >= scn.trials:
        raise RerunError(f"{run_dir}: trial {trial} is out of range (the run has {scn.trials} trials, 0-{scn.trials - 1})")
    co = engine.compute_chunk(scn.model_dump_json(), np.array([trial]), "full", kernels)
    recomputed = co.trials_table.to_pandas()
    lines = [f"{scn.name}: trial {trial} (root seed {scn.seed}, SeedSequence spawn key ({trial},))"]
    identical = True
    stored = None
    tp = run_dir / "trials.parquet"
    if tp.is_file():
        stored = pd.read_parquet(tp)
        stored = stored[stored["trial"] == trial].reset_index(drop=True)
    if scn.dispersions is not None and scn.dispersions.specs:
        from ..config.dispersions import units

        row0 = recomputed.iloc[0]
        vals = ", ".join(f"{k}={row0[k]:.6g} {u if u != '-' else ''}".rstrip() for k, u in units(scn).items() if k in row0)
        lines.append(f"  dispersed ({scn.dispersions.sampling}): {vals}")
        if scn.dispersions.sampling == "sobol":
            from ..sim.dispersions import noise_streams

            lines.append(f"  noise stream of its Saltelli block: spawn key ({int(noise_streams(scn, [trial])[0])},)")
    for _, row in recomputed.iterrows():
        errs = ", ".join(f"{n}={row[n]:.4g}" for n in tables.ERROR_NAMES)
        status = "diverged at step %d (%s)" % (row["diverged_step"], row["diverged_reason"]) if row["diverged"] else "ok"
        lines.append(f"  {row['filter']}: {errs}; {status}")
    if stored is not None and len(stored):
        same = recomputed.equals(stored)
        identical = bool(same)
        lines.append("identical to trials.parquet" if same else "DIFFERS from trials.parquet")
        run_blas, own_blas = engine.recorded_blas(run_dir), engine.blas_kernels()
        if run_blas is not None and run_blas != own_blas:
            lines.append(f"note: the run's BLAS kernels ({run_blas}) are not this process's ({own_blas}): their "
                         "round-off differs (the last digits, and a trial on the edge of a rule)")  # fmt: skip
    else:
        lines.append("(trial not in trials.parquet yet: nothing to compare)")
    if out is not None:
        out = Path(out)
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            store.write_parquet(out, co.timeseries_table, {"stereopose_mc.table": "timeseries", "trial": str(trial),
                                "stereopose_mc.seed": str(scn.seed)}, units=tables.COLUMN_UNITS)  # fmt: skip
        except OSError as exc:
            raise RerunError(f"--out {out}: cannot write it ({exc.strerror})") from None
        lines.append(f"time series -> {out}")
    return RerunResult(recomputed, identical, lines)
