"""Calibrate a filter's Q, R and P0 from Monte Carlo NEES/NIS (``spmc tune``).

What is searched (``space``, the CLI's ``--tune``, default ``q``):

- ``q``: the six Q blocks (rho, rho_dot, omega, q, feature_points, k) of the filter's
  ``process_noise``, each its own value;
- ``r``: one factor on the filter's measurement noise sigmas, image and image velocity
  (flow) together (and the disparity channel's with the image's, when it is on);
  ``r_image`` / ``r_flow``: a factor on each alone (both given: separately). The factor
  multiplies the sigma the filter uses today (its own ``measurement_noise`` or the
  truth's); the tuned entry writes the result as the filter's ``measurement_noise``
  (``image_sigma_px`` / ``flow_sigma_pxps`` with a pixel camera, else ``image_sigma`` /
  ``flow_sigma``);
- ``p0``: one factor per block of the scenario's ``initial_covariance``; ``p0_all``: one
  factor on all blocks. ``initial_covariance`` is both the filters' ``P0`` and the
  spread of the thesis's start draw ``x_hat(0) ~ N(truth, P0)`` (``sim/measurements.py``):
  scaling it scales the drawn start errors with it (a scenario's fixed offsets, e.g. its
  dispersions about the nominal values, do not scale).

Every evaluation runs the scenario the tuned values make (:func:`scenario_of`, values to
3 significant digits, as written) through the engine's chunk function
(``mc.engine.compute_chunk``: dispersions, truth model, faults, gating, the
measurement-based start, on ``kernels``), reduced to the tuned filter (plus the first
filter when the measurement-based start takes its R from it), with ``trials = N + M``:
the tuning trials are ``0 … N-1`` and the held-back check trials ``N … N+M-1`` of
``spmc run --trials N+M`` (trial ``j`` always draws from the ``j``-th SeedSequence child:
evaluations are paired and the search deterministic). Its statistics come from the
``trials.parquet`` columns ``spmc run`` writes: ``lost``, ``inconsistent``,
``nees_*_mean`` / dof, ``nis_ratio_mean`` and the six errors, medians over the trials that
were not lost. The cost of a tuning is

    J = sum_b log(N_b)^2 + log(N_gauge)^2 + 4 log(NIS)^2
        + 10 sum_e max(0, log(E_e / E_e,start) - log 1.1)^2 + 10 (lost / trials)

with ``N_b`` the median over trials of the time-averaged block NEES per dof (1 for a
consistent filter), ``NIS`` the median time-averaged NIS per dof and ``E_e`` the median
per-trial errors (accuracy may not get worse than 10 % of the starting tuning's without
cost); ``inconsistent`` flags are reported, not counted. Coordinate search: every Q block
together, then each Q block in turn, then the R factor(s), then all P0 factors together
and each in turn, is scaled by ``10^(+-step)`` and the move kept if ``J`` decreases (by
more than 0.1 %); after a sweep with no move the step halves, from ``initial_step``
decades down to ``min_step``; at most ``max_evaluations`` evaluations (the two held-back
evaluations, start and tuned, come on top). A Q block that is 0 starts from a floor
(``FLOORS``, the scale of the defaults' smallest nonzero entries) when the search tries to
raise it.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np
import pandas as pd

from ..config.resolve import DEG, filter_setup_of, process_noise_of, pseudo_unmodelled_var, setup_of
from ..config.schema import Scenario
from ..config.sensor import feature_count
from ..core import errorstate as es
from ..core.layout import n_state
from ..mc import engine
from ..rundir.tables import ERROR_NAMES

BLOCKS = ("rho", "rho_dot", "omega", "q", "feature_points", "k")
KEYS = {"rho": "rho_m2", "rho_dot": "rho_dot_m2ps2", "omega": "omega_deg2ps2", "q": "q",
        "feature_points": "feature_points_m2", "k": "k"}  # fmt: skip
FLOORS = {"rho": 1e-12, "rho_dot": 1e-14, "omega": 1e-12, "q": 1e-14, "feature_points": 1e-12, "k": 1e-12}
SPACES = ("q", "r", "r_image", "r_flow", "p0", "p0_all")  # the tokens of --tune


class TuneError(Exception):
    """Bad input to the tuner (unknown filter label, ...)."""


@dataclass
class Evaluation:
    """One tuning's statistics over a set of trials (the tuning ones or the held-back ones)."""

    params: dict[str, float]  # "Q.<block>": variance (scenario units); "R", "R.image", "P0", "P0.<block>": factors
    nees: dict[str, float]  # median NEES/dof per key of errorstate.nees_dof
    nis: float
    errors: dict[str, float]  # median per-trial errors
    lost: int
    inconsistent: int = 0
    trials: int = 0
    cost: float = float("nan")
    trial_ids: tuple[int, ...] = ()  # the trial indices counted

    @property
    def process_noise(self) -> dict[str, float]:
        """The Q blocks in the scenario's keys and units."""
        return {KEYS[b]: v for b in BLOCKS if (v := self.params.get(f"Q.{b}")) is not None}


@dataclass
class TuneResult:
    before: Evaluation  # on the tuning trials
    after: Evaluation
    evaluations: int
    history: list[Evaluation] = field(default_factory=list)
    check_before: Evaluation | None = None  # on the held-back trials
    check_after: Evaluation | None = None
    space: tuple[str, ...] = ("q",)
    scenario: Scenario | None = None  # the input scenario with the tuned values (every filter kept)


def parse_space(space: str | Iterable[str]) -> tuple[str, ...]:
    """``"q,r,p0"`` -> ``("q", "r", "p0")``, checked (:class:`TuneError` in one line)."""
    tokens = [t.strip().lower() for t in (space.split(",") if isinstance(space, str) else space)]
    tokens = [t for t in tokens if t]
    bad = [t for t in tokens if t not in SPACES]
    if bad or not tokens:
        raise TuneError(f"--tune: {'unknown ' + repr(bad[0]) if bad else 'nothing to tune'} "
                        f"(a comma-separated list of {', '.join(SPACES)})")  # fmt: skip
    if "r" in tokens and ({"r_image", "r_flow"} & set(tokens)):
        raise TuneError("--tune: r (one shared R factor) and r_image / r_flow (separate ones) exclude each other")
    if "p0" in tokens and "p0_all" in tokens:
        raise TuneError("--tune: p0 (a factor per block) and p0_all (one shared factor) exclude each other")
    return tuple(dict.fromkeys(tokens))


def start_params(scn: Scenario, index: int, space: tuple[str, ...]) -> dict[str, float]:
    """The search's starting point: today's Q values (those ``process_noise: auto`` resolves to), R and P0 factors
    1."""
    p: dict[str, float] = {}
    if "q" in space:
        pn = process_noise_of(scn.filters[index].process_noise, setup_of(scn))
        p.update({f"Q.{b}": float(getattr(pn, KEYS[b])) for b in BLOCKS})
    if "r" in space:
        p["R"] = 1.0
    p.update({f"R.{c}": 1.0 for c in ("image", "flow") if f"r_{c}" in space})
    if "p0" in space:
        p.update({f"P0.{b}": 1.0 for b in BLOCKS})
    if "p0_all" in space:
        p["P0"] = 1.0
    return p


def _sig3(v: float) -> float:
    return float(f"{v:.3g}")


def scenario_of(scn: Scenario, index: int, params: dict[str, float]) -> Scenario:
    """``scn`` with filter ``index``'s Q, R and the scenario's P0 set from ``params`` (values to 3 significant
    digits, as the tuned YAML writes them). Parameters absent from ``params`` leave their keys as they are."""
    d = scn.model_dump(mode="json")
    f = d["filters"][index]
    pn = {KEYS[b]: _sig3(params[f"Q.{b}"]) for b in BLOCKS if f"Q.{b}" in params}
    if pn:  # tuned values in full: an ``auto`` entry's derived Q is in them, so ``auto`` goes
        if f["process_noise"].get("auto"):  # and with it auto's widening of the pseudo rows: kept as the filter's own
            s = setup_of(scn)
            if pseudo_unmodelled_var(scn.filters[index].process_noise, s) > 0:
                mn = dict(f.get("measurement_noise") or {})
                mn["angular_acceleration_sigma_radps2"] = _sig3(filter_setup_of(scn.filters[index], s).sigma_alpha)
                f["measurement_noise"] = mn
        f["process_noise"] = {**f["process_noise"], **pn, "auto": False}
    a_img = params.get("R", params.get("R.image"))
    a_flow = params.get("R", params.get("R.flow"))
    if a_img is not None or a_flow is not None:
        s = setup_of(scn)
        fs = filter_setup_of(scn.filters[index], s)  # the sigmas the filter uses today (normalized units)
        mn = dict(f.get("measurement_noise") or {})
        px = s.sensor.pixels.f_px if s.sensor.pixels is not None else None
        for a, sigma, key, key_px in ((a_img, fs.sigma_image, "image_sigma", "image_sigma_px"),
                                      (a_flow, fs.sigma_flow, "flow_sigma", "flow_sigma_pxps")):  # fmt: skip
            if a is None:
                continue
            if px is None:
                mn[key] = _sig3(a * sigma)
            else:  # a pixel camera: the filter's sigma in pixels (it replaces the normalized key)
                mn[key], mn[key_px] = None, _sig3(a * sigma * px)
        if a_img is not None and scn.measurements.disparity:
            mn["disparity_sigma"] = _sig3(a_img * fs.sigma_disparity)
        f["measurement_noise"] = mn
    p0 = d["initial_covariance"]
    for b in BLOCKS:
        a = params.get("P0", params.get(f"P0.{b}"))
        if a is not None:
            p0[KEYS[b]] = _sig3(a * float(getattr(scn.initial_covariance, KEYS[b])))
    return Scenario.model_validate(d)


def _eval_scenario(tuned: Scenario, index: int, n_trials: int) -> Scenario:
    """``tuned`` with only the filters the tuned one's trials depend on, and ``n_trials`` trials."""
    keep = [index]
    if index and tuned.initial_estimate.method == "measurements":
        keep = [0, index]  # the measurement-based start uses the first filter's R (mc/trial.py, mc/dispersed.py)
    return tuned.model_copy(update={"filters": [tuned.filters[i] for i in keep], "trials": n_trials})


def _evaluate(scn: Scenario, label: str, params: dict[str, float], trials: np.ndarray, kernels: str,
              jobs: int = 1) -> Evaluation:  # fmt: skip
    """The trials ``trials`` of ``scn`` (already tuned and reduced), as ``spmc run`` computes them (its chunks on
    ``jobs`` cores: ``engine.compute_chunks``); statistics of filter ``label`` from its ``trials.parquet`` columns:
    medians over the trials that were not lost."""
    opts = engine.RunOptions(jobs=jobs, kernels=kernels, timeseries="none")
    parts = [co.trials_table.to_pandas() for co in engine.compute_chunks(scn, trials, opts)]
    df = pd.concat(parts, ignore_index=True)
    df = df[df["filter"] == label]
    ok = ~df["lost"].to_numpy(bool)

    def med(col: str) -> float:
        v = df[col].to_numpy(float)[ok]
        v = v[np.isfinite(v)]
        return float(np.median(v)) if v.size else float("nan")

    dofs = es.nees_dof(n_state(feature_count(scn)))
    nees = {k: med(f"{k}_mean") / d for k, d in dofs.items()}
    errs = {e: med(e) if ok.any() else float("inf") for e in ERROR_NAMES}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        nis = med("nis_ratio_mean")
    return Evaluation(dict(params), nees, nis, errs, int((~ok).sum()), int(df["inconsistent"].sum()), len(df),
                      trial_ids=tuple(int(t) for t in df["trial"]))  # fmt: skip


def _cost(ev: Evaluation, ref: Evaluation, trials: int) -> float:
    logs = [np.log(ev.nees[k]) for k in ev.nees if k != "nees"]
    if not np.all(np.isfinite(logs)) or not np.isfinite(ev.nis):
        return float("inf")
    J = float(np.sum(np.square(logs))) + 4.0 * float(np.log(ev.nis)) ** 2
    for e in ERROR_NAMES:
        r = ev.errors[e] / ref.errors[e] if ref.errors[e] > 0 else 1.0
        J += 10.0 * max(0.0, float(np.log(r)) - np.log(1.1)) ** 2 if np.isfinite(r) else np.inf
    return J + 10.0 * ev.lost / trials


def _moves(params: dict[str, float]) -> list[tuple[str, list[str]]]:
    """The coordinate search's groups, in order: Q all, each Q block, R, P0 all, each P0 block."""
    q = [k for k in params if k.startswith("Q.")]
    r = [k for k in params if k == "R" or k.startswith("R.")]
    p0 = [k for k in params if k == "P0" or k.startswith("P0.")]
    out = ([("Q", q)] if len(q) > 1 else []) + [(k, [k]) for k in q] + [(k, [k]) for k in r]
    return out + ([("P0", p0)] if len(p0) > 1 else []) + [(k, [k]) for k in p0]


def tune(scn: Scenario, label: str, trials: int = 30, max_evaluations: int = 40, min_step: float = 0.25,
         initial_step: float = 2.0, progress: Callable[[int, Evaluation, str], None] | None = None,
         kernels: str = engine.DEFAULT_KERNELS, space: str | Iterable[str] = ("q",),
         check_trials: int | None = None, jobs: int = 1) -> TuneResult:  # fmt: skip
    """Coordinate search of filter ``label``'s Q / R / P0 scales (see the module docstring) on ``kernels``,
    on trials ``0 … trials-1``; then the start and the result on the held-back trials
    ``trials … trials+check_trials-1`` (default ``check_trials = trials``; 0: no check). Each evaluation's trials
    run on ``jobs`` cores (the same results for any ``jobs``)."""
    labels = [f.label for f in scn.filters]
    if label not in labels:
        raise TuneError(f"no filter labelled {label!r} in scenario {scn.name!r} (its filters: {', '.join(labels)})")
    if trials < 2:
        raise TuneError("--trials must be at least 2")
    check_trials = trials if check_trials is None else check_trials
    if check_trials < 0:
        raise TuneError("--check-trials must be at least 0")
    space = parse_space(space)
    index = labels.index(label)
    ids, held = np.arange(trials), np.arange(trials, trials + check_trials)
    n_eval = 0

    def evaluate(params: dict[str, float], which: np.ndarray) -> Evaluation:
        scn_eval = _eval_scenario(scenario_of(scn, index, params), index, trials + check_trials)
        try:
            return _evaluate(scn_eval, label, params, which, kernels, jobs)
        except engine.RunError as exc:
            raise TuneError(str(exc)) from None

    def run(params: dict[str, float]) -> Evaluation:
        nonlocal n_eval
        n_eval += 1
        return evaluate(params, ids)

    p_start = start_params(scn, index, space)
    before = run(p_start)
    before.cost = _cost(before, before, trials)
    if progress:
        progress(n_eval, before, "start")
    best, history = before, [before]
    step = initial_step
    while step >= min_step and n_eval < max_evaluations:
        moved = False
        for name, group in _moves(p_start):
            for sign in (+1.0, -1.0):
                if n_eval >= max_evaluations:
                    break
                p = dict(best.params)
                for k in group:
                    if p[k] > 0 or sign > 0:
                        p[k] = (p[k] if p[k] > 0 else _floor(k.removeprefix("Q."))) * 10.0 ** (sign * step)
                if p == best.params:
                    continue
                ev = run(p)
                ev.cost = _cost(ev, before, trials)
                history.append(ev)
                keep = ev.cost < best.cost - 1e-3 * (1.0 + best.cost)  # a real improvement, not round-off
                if progress:
                    progress(n_eval, ev, f"{name} x10^{sign * step:+.2g}" + (" kept" if keep else ""))
                if keep:
                    best, moved = ev, True
                    break
        if not moved:
            step /= 2.0
    check = (None, None)
    if check_trials:
        check = tuple(evaluate(p, held) for p in (before.params, best.params))
        for ev in check:
            ev.cost = _cost(ev, check[0], check_trials)
    return TuneResult(before, best, n_eval, history, check[0], check[1], space,
                      scenario_of(scn, index, best.params))  # fmt: skip


def _floor(block: str) -> float:
    """A starting value for a zero Q block, in the scenario's units (omega in deg^2/s^2)."""
    return FLOORS[block] / (DEG**2 if block == "omega" else 1.0)


def comparison_table(before: Evaluation, after: Evaluation) -> pd.DataFrame:
    """Before / after: trials, lost and inconsistent counts, median NEES/dof per block, full and gauge-projected,
    NIS/dof, median errors (medians over the trials not lost), cost."""
    rows = []
    for name, ev in (("before", before), ("after", after)):
        row: dict[str, object] = {"tuning": name, "trials": ev.trials, "lost": ev.lost, "inconsistent": ev.inconsistent,
                                  "medians over (not lost)": ev.trials - ev.lost}  # fmt: skip
        row.update({f"NEES/dof {k.removeprefix('nees_') if k != 'nees' else 'full'}": v for k, v in ev.nees.items()})
        row["NIS/dof"] = ev.nis
        row.update({f"median {e}": v for e, v in ev.errors.items()})
        row["cost"] = ev.cost
        rows.append(row)
    return pd.DataFrame(rows).set_index("tuning").T.astype(float)


def tuned_entry(scn: Scenario, label: str, res: TuneResult) -> dict:
    """The tuned filter entry (``process_noise`` in full; ``measurement_noise`` when R was tuned), YAML-ready."""
    tuned = res.scenario if res.scenario is not None else scn
    f = next(f for f in tuned.filters if f.label == label)
    d = {"type": f.type, **f.model_dump(mode="json", exclude_defaults=True)}
    d["process_noise"] = f.process_noise.model_dump(mode="json")
    if any(k == "R" or k.startswith("R.") for k in res.after.params):
        d["measurement_noise"] = f.measurement_noise.model_dump(mode="json", exclude_none=True)
    return d


def tuned_yaml_data(label: str, res: TuneResult) -> dict:
    """``{"filters": [entry]}``, plus the ``initial_covariance`` block when P0 was tuned."""
    assert res.scenario is not None
    out: dict = {"filters": [tuned_entry(res.scenario, label, res)]}
    if any(k == "P0" or k.startswith("P0.") for k in res.after.params):
        out["initial_covariance"] = res.scenario.initial_covariance.model_dump(mode="json")
    return out
