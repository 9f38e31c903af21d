"""Calibrate a filter's process noise from Monte Carlo NEES/NIS (``spmc tune``).

The search is over ``log10`` scale factors ``s_b`` of the six Q blocks (rho, rho_dot,
omega, q, feature_points, k) of one filter entry, every evaluation running the same
``trials`` trials (trial ``j`` always draws from the ``j``-th SeedSequence child: the
search is deterministic and its evaluations are paired). The cost of a tuning is

    J = sum_b log(N_b)^2 + log(N_gauge)^2 + 4 log(NIS)^2
        + 10 sum_e max(0, log(E_e / E_e,start) - log 1.1)^2 + 10 (lost / trials)

with ``N_b`` the median over trials of the time-averaged block NEES per dof (1 for a
consistent filter), ``NIS`` the median time-averaged NIS per dof and ``E_e`` the median
per-trial errors (accuracy may not get worse than 10 % of the starting tuning's without
cost). Coordinate search: every block together, then each block in turn, is scaled by
``10^(+-step)`` and the move kept if ``J`` decreases (by more than 0.1 %); after a sweep
with no move the step halves, from ``initial_step`` decades down to ``min_step``; at most ``max_evaluations`` evaluations. A block whose Q is 0 starts
from a floor (``FLOORS``, the scale of the defaults' smallest nonzero entries) when the
search tries to raise it.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import pandas as pd

from ..config.resolve import DEG, FilterSetup, block_diag
from ..config.schema import ProcessNoiseConfig, Scenario
from ..mc import engine
from ..core import errorstate as es
from ..mc.trial import run_chunk
from ..rundir.tables import ERROR_NAMES

BLOCKS = ("rho", "rho_dot", "omega", "q", "feature_points", "k")
KEYS = {"rho": "rho_m2", "rho_dot": "rho_dot_m2ps2", "omega": "omega_deg2ps2", "q": "q",
        "feature_points": "feature_points_m2", "k": "k"}  # fmt: skip
FLOORS = {"rho": 1e-12, "rho_dot": 1e-14, "omega": 1e-12, "q": 1e-14, "feature_points": 1e-12, "k": 1e-12}


class TuneError(Exception):
    """Bad input to the tuner (unknown filter label, ...)."""


@dataclass
class Evaluation:
    """One tuning's statistics over the tuning trials."""

    process_noise: dict[str, float]  # the scenario's keys and units
    nees: dict[str, float]  # median NEES/dof per key of errorstate.nees_dof
    nis: float
    errors: dict[str, float]  # median per-trial errors
    lost: int
    cost: float = float("nan")


@dataclass
class TuneResult:
    before: Evaluation
    after: Evaluation
    evaluations: int
    history: list[Evaluation] = field(default_factory=list)


def _evaluate(prep: engine.Prepared, index: int, pn: dict[str, float], trials: np.ndarray,
              kernels: str = engine.DEFAULT_KERNELS) -> Evaluation:  # fmt: skip
    """Medians over the converged trials of the window-averaged NEES/dof (per key), NIS/dof and errors."""
    scn, setup = prep.scenario, prep.setup
    fs: FilterSetup = dataclasses.replace(prep.filters[index], Q_diag=block_diag(ProcessNoiseConfig(**pn), setup.n_points))
    r = run_chunk(scn.seed, trials, setup, prep.truth, prep.exact, [fs], prep.bounds, kernels).runs[0]
    w = prep.truth.t >= setup.window_start - 1e-9
    ok = r.diverged_step < 0
    series = {"nees": r.nees, **r.nees_parts}

    def med(a: np.ndarray) -> float:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            v = np.nanmean(a[ok][:, w], axis=1) if ok.any() else np.array([])
        v = v[np.isfinite(v)]
        return float(np.median(v)) if v.size else float("nan")

    nees = {k: med(series[k]) / d for k, d in es.nees_dof(setup.x0.size).items()}
    with np.errstate(all="ignore"):
        nis = med(np.where(r.nis_dof > 0, r.nis / np.maximum(r.nis_dof, 1), np.nan))
        errs = {e: med(r.errors[..., j]) if ok.any() else float("inf") for j, e in enumerate(ERROR_NAMES)}
    return Evaluation(dict(pn), nees, nis, errs, int((~ok).sum()))


def _cost(ev: Evaluation, ref: Evaluation, trials: int) -> float:
    logs = [np.log(ev.nees[k]) for k in ev.nees if k != "nees"]
    if not np.all(np.isfinite(logs)) or not np.isfinite(ev.nis):
        return float("inf")
    J = float(np.sum(np.square(logs))) + 4.0 * float(np.log(ev.nis)) ** 2
    for e in ERROR_NAMES:
        r = ev.errors[e] / ref.errors[e] if ref.errors[e] > 0 else 1.0
        J += 10.0 * max(0.0, float(np.log(r)) - np.log(1.1)) ** 2 if np.isfinite(r) else np.inf
    return J + 10.0 * ev.lost / trials


def tune(scn: Scenario, label: str, trials: int = 30, max_evaluations: int = 40, min_step: float = 0.25,
         initial_step: float = 2.0, progress: Callable[[int, Evaluation, str], None] | None = None,
         kernels: str = engine.DEFAULT_KERNELS) -> TuneResult:  # fmt: skip
    """Coordinate search of the Q block scales of filter ``label`` (see the module docstring) on ``kernels``."""
    labels = [f.label for f in scn.filters]
    if label not in labels:
        raise TuneError(f"no filter labelled {label!r} in scenario {scn.name!r} (its filters: {', '.join(labels)})")
    if trials < 2:
        raise TuneError("--trials must be at least 2")
    index = labels.index(label)
    prep = engine.prepare(scn)
    ids = np.arange(trials)
    pn0 = scn.filters[index].process_noise.model_dump()
    n_eval = 0

    def run(pn):
        nonlocal n_eval
        n_eval += 1
        return _evaluate(prep, index, pn, ids, kernels)

    before = run(pn0)
    before.cost = _cost(before, before, trials)
    if progress:
        progress(n_eval, before, "start")
    best, history = before, [before]
    step = initial_step
    while step >= min_step and n_eval < max_evaluations:
        moved = False
        for b in ("all",) + BLOCKS:
            for sign in (+1.0, -1.0):
                if n_eval >= max_evaluations:
                    break
                pn = dict(best.process_noise)
                for bb in BLOCKS if b == "all" else (b,):
                    cur = pn[KEYS[bb]]
                    if cur > 0 or sign > 0:
                        pn[KEYS[bb]] = (cur if cur > 0 else _floor(bb)) * 10.0 ** (sign * step)
                if pn == best.process_noise:
                    continue
                ev = run(pn)
                ev.cost = _cost(ev, before, trials)
                history.append(ev)
                keep = ev.cost < best.cost - 1e-3 * (1.0 + best.cost)  # a real improvement, not round-off
                if progress:
                    progress(n_eval, ev, f"{b} x10^{sign * step:+.2g}" + (" kept" if keep else ""))
                if keep:
                    best, moved = ev, True
                    break
        if not moved:
            step /= 2.0
    return TuneResult(before, best, n_eval, history)


def _floor(block: str) -> float:
    """A starting value for a zero Q block, in the scenario's units (omega in deg^2/s^2)."""
    return FLOORS[block] / (DEG**2 if block == "omega" else 1.0)


def comparison_table(res: TuneResult) -> pd.DataFrame:
    """Before / after: median NEES/dof per block and gauge-projected, NIS/dof, errors, lost trials."""
    rows = []
    for name, ev in (("before", res.before), ("after", res.after)):
        row = {"tuning": name}
        row.update({f"NEES/dof {k.removeprefix('nees_') if k != 'nees' else 'full'}": v for k, v in ev.nees.items()})
        row["NIS/dof"] = ev.nis
        row.update({f"median {e}": v for e, v in ev.errors.items()})
        row["lost"] = ev.lost
        row["cost"] = ev.cost
        rows.append(row)
    return pd.DataFrame(rows).set_index("tuning").T


def tuned_entry(scn: Scenario, label: str, res: TuneResult) -> dict:
    """The filter entry with the tuned ``process_noise``, as plain YAML-ready data."""
    f = next(f for f in scn.filters if f.label == label)
    d = {"type": f.type, **f.model_dump(mode="json", exclude_defaults=True)}
    d["process_noise"] = {k: float(f"{v:.3g}") for k, v in res.after.process_noise.items()}
    return d
