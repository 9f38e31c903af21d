"""Trials measured by tracks: ``measurements.source: images`` or ``tracks`` (docs/images.md).

With ``images`` each trial's stereo frames are rendered (once per campaign for a shared truth), exposed with
the trial's own sensor noise and tracked (``sim/images.py``); with ``tracks`` the rows come from the user's
file (``sim/tracks_file.py``: its ``trial`` column, or the same tracks for every trial). Either way the tracks
fill the filters' feature slots (``sim/slots.py`` assigns them, ``filters/slots.py`` initializes and frees them)
and every filter of the scenario runs on the same slot measurements, initial estimate and angular-acceleration
noise (the trial's own streams, as with the point model).

The truth: the simulated one for ``images``; for ``tracks`` the ``truth_file``'s states (the inertia ratios from
the scenario), or none (every error and NEES NaN: only what the filter itself detects, ``lost``, is reported).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Callable

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from ..config.resolve import FilterSetup, Setup
from ..config.schema import Scenario
from ..config.sensor import pixel_camera_of
from ..filters import slots as fsl
from ..core import dynamics
from ..core import layout as lay
from ..core import quaternion as qt
from ..core import state as st
from ..core.orbit import leader_kinematics
from ..sim import measurements as meas
from ..sim import slots as ssl
from ..sim import tracks_file
from ..sim.truth import Truth
from .trial import Bounds, ChunkResult, run_filter

Array = NDArray[np.float64]


def file_truth(scn: Scenario, setup: Setup, truth: Truth) -> Truth:
    """The truth of a ``tracks`` source: ``truth_file``'s states on the scenario's steps (the inertia ratios from the
    scenario, the relative angular acceleration from the model's dynamics, as for a simulated truth); without a
    truth file, NaN (no error can be computed). ``truth``: the scenario's simulated truth (times, leader)."""
    path = scn.measurements.tracks.truth_file
    x = np.full_like(truth.x, np.nan)
    if path is None:
        return dataclasses.replace(truth, x=x, alpha=np.full_like(truth.alpha, np.nan))
    df = tracks_file.read_truth(path, setup.dt)
    if "trial" in df and df["trial"].nunique() > 1:
        raise tracks_file.TracksFileError(f"{path}: column 'trial': one truth for every trial is supported, "
                                          f"this file has {df['trial'].nunique()}")  # fmt: skip
    K = setup.steps
    steps = df["step"].to_numpy(np.int64)
    missing = np.setdiff1d(np.arange(K + 1), steps)
    if missing.size:
        raise tracks_file.TracksFileError(f"{path}: column 'step': no row for step {int(missing[0])} (the scenario "
                                          f"has steps 0..{K})")  # fmt: skip
    rows = df.set_index("step").loc[np.arange(K + 1), list(tracks_file.STATE_COLUMNS)].to_numpy(float)
    x = truth.x.copy()
    x[:, : lay.POINTS] = rows
    x[:, st.QUAT] = qt.normalize(x[:, st.QUAT])
    lk = leader_kinematics(setup.orbit, truth.t)
    alpha = np.ascontiguousarray(dynamics.f(x, lk.r, lk.nu_dot, lk.nu_ddot, setup.orbit.mu)[:, st.OMEGA])
    return dataclasses.replace(truth, x=x, alpha=alpha)


@functools.lru_cache(maxsize=2)
def _file_tracks(path: str, dt: float) -> pd.DataFrame:
    return tracks_file.read_tracks(path, dt)


def file_tracks(scn: Scenario, setup: Setup) -> pd.DataFrame:
    """The ``tracks`` source's file, read and checked once per process (``TracksFileError``: one line)."""
    return _file_tracks(scn.measurements.tracks.file, setup.dt)


def tracks_for(scn: Scenario, setup: Setup, truth: Truth, trials: NDArray[np.int64],
               tick: Callable[[int], None] | None = None) -> pd.DataFrame:  # fmt: skip
    """The track table of ``trials`` (a ``trial`` column): rendered and tracked (``images``), or the file's rows
    (``tracks``: its trial ``j``'s, or trial 0's for every trial when the file has one trial).

    ``tick(n)``: progress in trial-steps (``run_filter``'s unit); an images campaign counts a trial's steps of
    every filter when its tracking ends (tracking is most of its time), and its filters then count nothing.
    """
    if scn.measurements.source == "images":
        from ..sim import images  # OpenCV and the renderer: imported only by image campaigns

        per_trial = setup.steps * len(scn.filters)

        def progress(stage: str, done: int, total: int) -> None:
            if tick is not None and stage == "track":
                tick(per_trial)

        return images.campaign_tracks(scn, setup, truth, trials, scn.seed, progress=progress)
    df = file_tracks(scn, setup)
    if df["trial"].nunique() == 1:
        base = df.drop(columns="trial")
        return pd.concat([base.assign(trial=int(j)) for j in trials], ignore_index=True)[df.columns]
    return df[df["trial"].isin(np.asarray(trials))].reset_index(drop=True)


def dispersed_tracks(scenarios: list[Scenario], setups: list[Setup], truth: Truth, trials: NDArray[np.int64],
                     seed: int, tick: Callable[[int], None] | None = None) -> pd.DataFrame:  # fmt: skip
    """The tracks of dispersed trials: each rendered from its own scenario (shape, camera, Sun) along its own truth
    (``truth.x (B, K+1, n)``, rows aligned with ``trials``), with its own noise stream; ``tick`` as ``tracks_for``."""
    from ..sim import images  # OpenCV and the renderer: imported only by image campaigns

    out = []
    for i, (s, st_, j) in enumerate(zip(scenarios, setups, trials)):
        one = dataclasses.replace(truth, x=truth.x[i : i + 1])
        out.append(images.campaign_tracks(s, st_, one, [int(j)], seed))
        if tick is not None:
            tick(st_.steps * len(s.filters))
    return pd.concat(out, ignore_index=True)


def used_rows(tracks: pd.DataFrame) -> pd.DataFrame:
    """The rows the filters use: every track's rows but its first (its detection).

    A track enters its slot at its first *tracked* row. The detection's position differs from where the tracker then
    holds the feature by a fraction of a pixel (``docs/measure_tracker_noise.py`` prints the jump): born from the
    detection, a slot would start that far off, and the first image velocity (detection to first tracked frame)
    would carry the jump; the velocities of every slot born at the start then bias omega at the first update.
    """
    first = tracks.groupby(["trial", "track_id"], sort=False)["step"].transform("min")
    return tracks[tracks["step"].to_numpy() > first.to_numpy()]


@dataclasses.dataclass(frozen=True)
class SlotData:
    """The slot measurements of a chunk's trials (``B`` trials, ``K+1`` steps, ``N`` slots)."""

    y: Array  # (B, K+1, N, 8) normalized image units; 0 where not measured
    visible: NDArray[np.bool_]  # (B, K+1, N): measured and not born at the step (births initialize, not update)
    schedule: fsl.Schedule
    sigma: Array  # (B, K+1, N, 2): the rows' own [position, velocity] sigma, normalized (NaN: not given)
    unused: NDArray[np.int64]  # (B,) tracks that found no free slot

    def extra_var(self, fs: FilterSetup) -> Array | None:
        """``(B, K+1, N, 8)``: how much the rows' own variance (``sigma_px``, ``sigma_pxps``) exceeds the filter's
        R, or None when no row gives one."""
        if not np.isfinite(self.sigma).any():
            return None
        base = np.array([fs.sigma_image] * 4 + [fs.sigma_flow] * 4)
        s = np.repeat(self.sigma, 4, axis=-1)  # [position x4, velocity x4]
        return np.where(np.isfinite(s), np.maximum(s * s - base * base, 0.0), 0.0)


def slot_data(tracks: pd.DataFrame, trials: NDArray[np.int64], setup: Setup, scn: Scenario) -> SlotData:
    """``SlotData`` of ``trials`` from a track table with a ``trial`` column (``scn``: whose camera converts the
    pixels)."""
    cam = pixel_camera_of(scn)
    K, N = setup.steps, setup.n_points
    B = len(trials)
    y = np.zeros((B, K + 1, N, 8))
    vis = np.zeros((B, K + 1, N), bool)
    occ = np.zeros((B, K + 1, N), bool)
    born = np.zeros((B, K + 1, N), bool)
    body = np.full((B, K + 1, N, 3), np.nan)
    sig = np.full((B, K + 1, N, 2), np.nan)
    unused = np.zeros(B, np.int64)
    groups = dict(tuple(used_rows(tracks).groupby("trial", sort=False))) if len(tracks) else {}
    for i, j in enumerate(trials):
        df = groups.get(int(j), tracks.iloc[:0])
        a = ssl.assign_slots(df, N, K)
        m = ssl.slot_measurements(df, a, cam)
        occ[i] = a.track != ssl.FREE
        # a birth needs the track's stereo position
        born[i] = m.born & np.isfinite(m.y[..., :4]).all(-1)
        vis[i] = m.measured & ~born[i]
        y[i] = np.where(np.isfinite(m.y), m.y, 0.0)
        body[i] = m.body
        sig[i] = m.sigma
        unused[i] = a.unused.size
    return SlotData(y, vis, fsl.Schedule(occ, born, body), sig, unused)


def run_chunk(scn: Scenario, trials: NDArray[np.int64], setup: Setup, truth: Truth, exact: meas.Measurements,
              filters: list[FilterSetup], bounds: Bounds, tracks: pd.DataFrame, kernels: str = "numpy",
              tick: Callable[[int], None] | None = None) -> ChunkResult:  # fmt: skip
    """Every filter on the chunk's tracks (``tracks``: the chunk's rows, ``trial`` column)."""
    t0 = time.perf_counter()
    trials = np.asarray(trials)
    draws = meas.draw_trials(scn.seed, trials, setup.x0.size, setup.steps, setup.n_points)
    alpha = meas.noisy(setup, exact, draws).alpha  # the pseudo-measurement's input, as with the point model
    x0_hat = meas.initial_estimates(setup, draws)  # its points: the free slots' (a birth replaces them)
    d = slot_data(tracks, trials, setup, scn)
    runs = []
    for fs in filters:
        t1 = time.perf_counter()
        r = run_filter(x0_hat, setup, truth, d.y, alpha, d.visible, fs, bounds, None, None, kernels, tick,
                       slots=d.schedule, extra_var=d.extra_var(fs))  # fmt: skip
        r.runtime_s = np.full(len(trials), (time.perf_counter() - t1) / len(trials))
        runs.append(r)
    return ChunkResult(trials, runs, time.perf_counter() - t0, None)
