"""A chunk of dispersed trials: per-trial truth (batched), measurements, filters.

For a scenario with ``dispersions``, trial ``j``:

1. draws its dispersed values (``sim.dispersions``; its own dispersion stream or the
   plan's row ``j``) and validates the dispersed scenario: an invalid draw (e.g. a
   perigee below the ground or a feature behind the cameras) makes an *invalid trial*:
   every filter's row is kept, marked ``lost`` at step 0 with the reason
   ``invalid draw: ...`` and ``invalid = True``;
2. gets its truth: all valid trials of the chunk are propagated together
   (``sim.truth.simulate_truth_batch``, trial axis first);
3. draws its noise and initial-estimate error from its usual stream ``spawn_key=(j,)``
   (the same numbers as without dispersions; in ``sobol`` campaigns the stream of its
   Saltelli block, ``sim.dispersions.noise_streams``) on its exact measurements, made with
   the truth's (dispersed) camera and noise levels;
4. runs every filter with the filter's model: the nominal values, or the dispersed
   ones for keys with ``applies_to: both``. The initial estimate is centred on the
   nominal state, or on the dispersed true value for state keys
   (``truth_initial_state.*``, ``target.*``) with ``applies_to: both``, plus the
   ``N(0, P0)`` error. Trials whose filter models agree run as one batch (all of them,
   unless the camera, orbit or noise levels are dispersed with ``applies_to: both``),
   each with its own visibility (``trial.run_filter``: at each step, one update per pattern
   of visible features, or past 64 state columns on the compiled kernels one update with
   each trial's view as its row mask; the same numbers as the trial run alone).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from ..config.resolve import FilterSetup, Setup, filter_setup_of, setup_of
from ..config.schema import Scenario
from ..sim import dispersions as sd
from ..sim import measurements as meas
from ..sim.dispersions import exact_measurements, noisy_measurements, truth_of
from ..sim.truth import Truth
from ..filters.initialization import measurement_start
from ..sim.faults import Faults, apply_faults
from .trial import Bounds, ChunkResult, FilterRun, run_filter

if TYPE_CHECKING:
    from ..rundir.tables import Columns

INVALID_PREFIX = "invalid draw: "


def has_dispersions(scn: Scenario) -> bool:
    return scn.dispersions is not None and bool(scn.dispersions.specs)


def _empty_run(label: str, B: int, K1: int) -> FilterRun:
    return FilterRun(label, np.full((B, K1, 6), np.nan), np.full((B, K1), np.nan), np.full((B, K1), np.nan),
                     np.zeros((B, K1), int), np.zeros((B, K1), int), np.zeros((B, K1), bool), np.full(B, -1),
                     [""] * B, dof=np.zeros((B, K1), int), gated=np.zeros((B, K1), np.int64))  # fmt: skip


def _put(dst: FilterRun, src: FilterRun, rows: np.ndarray) -> None:
    for name in ("errors", "nees", "nis", "iterations", "converged", "lost_step", "inconsistent_step"):
        getattr(dst, name)[rows] = getattr(src, name)
    for r, reason, why in zip(rows, src.lost_reason, src.inconsistent_reason):
        dst.lost_reason[r], dst.inconsistent_reason[r] = reason, why
    for name, a in src.nees_parts.items():  # every block NEES and the gauge-projected one, per trial
        dst.nees_parts.setdefault(name, np.full(dst.nees.shape, np.nan))[rows] = a
    for name in ("axis_err", "axis_sigma"):
        a = getattr(src, name)
        if a is not None:
            if getattr(dst, name) is None:
                setattr(dst, name, np.full(dst.nees.shape + a.shape[2:], np.nan))
            getattr(dst, name)[rows] = a
    if src.k_sigma_ratio is not None:
        if dst.k_sigma_ratio is None:
            dst.k_sigma_ratio = np.full((dst.nees.shape[0], 2), np.nan)
        dst.k_sigma_ratio[rows] = src.k_sigma_ratio
    dst.nis_dof[rows] = src.nis_dof
    dst.state_dim = src.state_dim
    dst.dof[rows] = src.nis_dof if src.dof is None else src.dof
    if src.gated is not None:
        dst.gated[rows] = src.gated
    if src.nees_dof_steps is not None:  # feature slots: each NEES's dof per trial and step
        if dst.nees_dof_steps is None:
            dst.nees_dof_steps = {k: np.zeros((dst.nees.shape[0], v.shape[1]), v.dtype)
                                  for k, v in src.nees_dof_steps.items()}  # fmt: skip
        for k, v in src.nees_dof_steps.items():
            dst.nees_dof_steps[k][rows] = v


def _same_visibility(visible: np.ndarray) -> list[np.ndarray]:
    """The trials (positions, increasing) of each distinct visibility pattern ``visible (B, ...)``."""
    flat = visible.reshape(visible.shape[0], -1)
    _, inverse = np.unique(flat, axis=0, return_inverse=True)
    return [np.flatnonzero(inverse.ravel() == c) for c in range(int(inverse.max()) + 1)]


def _faults(setup: Setup, seed: int, trials: np.ndarray, y: np.ndarray, exact_y: np.ndarray, visible: np.ndarray):
    """``(y, kept, outlier)`` of ``sim.faults.apply_faults`` for trials with their own visibility ``(b, K+1, N)``
    (applied to the trials of each visibility pattern together: each trial's faults come from its own stream)."""
    y_out, kept, outlier = np.empty_like(y), np.empty(visible.shape, bool), np.empty(visible.shape, bool)
    for s in _same_visibility(visible):
        y_out[s], f = apply_faults(setup.sensor, seed, trials[s], y[s], exact_y[s], visible[s[0]])
        kept[s], outlier[s] = f.kept, f.outlier
    return y_out, kept, outlier


def _measurement_start(fsetup: Setup, fs: FilterSetup, y0: np.ndarray, visible0: np.ndarray, x_draw: np.ndarray):
    """``filters.initialization.measurement_start`` for trials with their own first-frame visibility ``(b, N)``."""
    b, n = x_draw.shape
    x0, P0 = np.empty((b, n)), np.empty((b, n, n))
    for s in _same_visibility(visible0):
        x0[s], P0[s] = measurement_start(fsetup, fs, y0[s], visible0[s[0]], x_draw[s])
    return x0, P0


def run_chunk(scn: Scenario, trials: np.ndarray, setup: Setup, bounds: Bounds,
              kernels: str = "numpy", tick=None, tracks_out: list | None = None,
              ) -> tuple[ChunkResult, sd.TrialDispersions]:  # fmt: skip
    """Every filter of ``scn`` on the dispersed trials ``trials`` (a ``ChunkResult`` in trial order;
    ``tick``: ``trial.run_filter``'s progress counter).

    ``measurements.source: images``: each valid trial's frames are rendered from its own dispersed scenario and
    truth, tracked, and its tracks fill the filters' feature slots (``mc/tracked.py``); their tables are appended to
    ``tracks_out``.
    """
    t0 = time.perf_counter()
    trials = np.asarray(trials, dtype=np.int64)
    B, K1 = trials.size, setup.steps + 1
    disp = sd.draw(scn, trials)
    labels = [f.label for f in scn.filters]
    runs = {lab: _empty_run(lab, B, K1) for lab in labels}
    valid = np.array([not r for r in disp.invalid])
    for i in np.flatnonzero(~valid):
        for r in runs.values():
            r.lost_step[i] = 0
            r.lost_reason[i] = INVALID_PREFIX + disp.invalid[i]
    rows = np.flatnonzero(valid)
    if rows.size:
        tsetups = [setup_of(disp.truth[i]) for i in rows]
        truth = truth_of(tsetups, setup.times, setup.truth_rtol)
        exact = exact_measurements(tsetups, truth)
        draws = meas.draw_trials(scn.seed, sd.noise_streams(scn, trials[rows]), setup.x0.size, setup.steps,
                                 setup.n_points)  # fmt: skip
        noisy = noisy_measurements(tsetups, exact, draws)
        faulty = setup.sensor.faults
        if faulty:  # the tracker's faults: the same per-trial fault stream as an undispersed run (sim/faults.py)
            kept_all = np.ones((B, K1, setup.n_points), bool)
            outlier_all = np.zeros((B, K1, setup.n_points), bool)
        fsetups = [setup_of(disp.filter_model[i]) for i in rows]
        x0_hat = meas.initial_estimates(setup, draws, np.stack([s.x0 for s in fsetups]))
        groups: dict[tuple, list[int]] = {}
        for g, i in enumerate(rows):
            groups.setdefault(disp.model_key[i], []).append(g)
        for members in groups.values():
            m = np.asarray(members)
            fsetup = fsetups[m[0]]
            filters: list[FilterSetup] = [filter_setup_of(f, fsetup) for f in scn.filters]
            vis_m = exact.visible[m]  # (b, K+1, N): each trial its own
            y_m, kept_m = noisy.y[m], None
            if faulty:
                y_m, kept_m, outlier_m = _faults(setup, scn.seed, trials[rows[m]], y_m, exact.y[m], vis_m)
                kept_all[rows[m]], outlier_all[rows[m]] = kept_m, outlier_m
            tg = Truth(t=truth.t, nu=truth.nu[m], nu_dot=truth.nu_dot[m], nu_ddot=truth.nu_ddot[m], x=truth.x[m],
                       alpha=truth.alpha[m])  # fmt: skip
            x0_m, P0_m = x0_hat[m], None
            if fsetup.initial_estimate == "measurements":  # the filters' own start from the first frame
                x0_m, P0_m = _measurement_start(fsetup, filters[0], y_m[:, 0], vis_m[:, 0], x0_m)
            slot = None
            if scn.measurements.source == "images":  # the trials' own renders and tracks in the feature slots
                from . import tracked  # OpenCV, pandas: only image campaigns import them

                slot = tracked.dispersed_tracks([disp.truth[rows[g]] for g in m], [tsetups[g] for g in m], tg,
                                                trials[rows[m]], scn.seed, tick)  # fmt: skip
                if tracks_out is not None:
                    tracks_out.append(slot)
                slot = tracked.slot_data(slot, trials[rows[m]], fsetup, disp.filter_model[rows[m[0]]])
            for fs in filters:
                t1 = time.perf_counter()
                if slot is not None:
                    r = run_filter(x0_m, fsetup, tg, slot.y, noisy.alpha[m], slot.visible, fs, bounds, None, None,
                                   kernels, None, slots=slot.schedule, extra_var=slot.extra_var(fs))  # fmt: skip
                else:
                    r = run_filter(x0_m, fsetup, tg, y_m, noisy.alpha[m], vis_m, fs, bounds, kept_m, P0_m, kernels,
                                   tick)  # fmt: skip
                _put(runs[fs.label], r, rows[m])
                runs[fs.label].runtime_s = (runs[fs.label].runtime_s if runs[fs.label].runtime_s is not None
                                            else np.zeros(B))  # fmt: skip
                runs[fs.label].runtime_s[rows[m]] = (time.perf_counter() - t1) / m.size
    for r in runs.values():
        if r.runtime_s is None:
            r.runtime_s = np.zeros(B)
    faults = Faults(kept_all, outlier_all) if rows.size and setup.sensor.faults else None
    return ChunkResult(trials, [runs[lab] for lab in labels], time.perf_counter() - t0, faults), disp


def with_columns(tc: Columns, disp: sd.TrialDispersions) -> Columns:
    """``trials_columns`` rows plus ``invalid`` and one column per dispersed scalar (by each row's trial)."""
    where = {int(t): i for i, t in enumerate(np.asarray(disp.trials).tolist())}
    pos = np.array([where[t] for t in tc["trial"].tolist()], dtype=np.int64)
    out = dict(tc)
    out["invalid"] = np.asarray(disp.invalid, bool)[pos]
    for name, v in disp.columns.items():
        out[name] = np.asarray(v)[pos]
    return out
