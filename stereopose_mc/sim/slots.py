"""Feature slots: which track each of the filter's ``N`` feature slots holds at each step, and its measurements.

The state keeps a fixed number ``N`` of feature points (``target.feature_slots``) so every kernel
keeps a fixed size. Tracks come and go (sim/tracker/klt.py, or your own file: sim/tracks_file.py);
:func:`assign_slots` decides, step by step:

1. a track whose last row was at an earlier step has ended: its slot is free from this step on;
2. the tracks first seen at this step take the lowest free slots, in increasing track id (the
   tracker numbers new tracks strongest first); a new track that finds no free slot is never
   used (it is counted in :attr:`SlotAssignment.unused`), not even when a slot frees later;
3. a track keeps its slot from its first row to its last (at a step in between without a row,
   the slot stays its own and is not measured).

The idealized point model is the special case of ``N`` tracks that live through the whole run.

:func:`slot_measurements` turns the pixel tracks into the filter's measurement arrays, in normalized
image units (``u = (col - c_x) / f_px``, config/sensor.py ``PixelCamera.normalized``) and the filter's
channel order ``[u_R, v_R, u_L, v_L, du_R, dv_R, du_L, dv_L]`` (core/camera.py ``CHANNELS``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from ..config.sensor import PixelCamera
from ..core.camera import CHANNELS

FREE = -1
PIXEL_COLUMNS = ("col_r", "row_r", "col_l", "row_l", "dcol_r", "drow_r", "dcol_l", "drow_l")  # as CHANNELS


@dataclass(frozen=True)
class SlotAssignment:
    track: NDArray[np.int64]  # (K+1, N): the track id in each slot at each step, FREE (-1) when empty
    unused: NDArray[np.int64]  # ids of the tracks that found no free slot (sorted)


def assign_slots(tracks: pd.DataFrame, n_slots: int, steps: int) -> SlotAssignment:
    """Slots of one trial's tracks (columns ``step``, ``track_id``; rows after ``steps`` are ignored)."""
    if n_slots < 1:
        raise ValueError(f"assign_slots: n_slots must be >= 1 (got {n_slots})")
    k = tracks["step"].to_numpy(dtype=np.int64)
    tid = tracks["track_id"].to_numpy(dtype=np.int64)
    keep = (k >= 0) & (k <= steps)
    life = pd.DataFrame({"k": k[keep], "id": tid[keep]}).groupby("id")["k"].agg(["min", "max"]).sort_index()
    born_at: dict[int, list[int]] = {}
    for i, first in zip(life.index.to_numpy(), life["min"].to_numpy()):
        born_at.setdefault(int(first), []).append(int(i))
    last = dict(zip(life.index.to_numpy().tolist(), life["max"].to_numpy().tolist()))
    slot = np.full((steps + 1, n_slots), FREE, np.int64)
    cur = np.full(n_slots, FREE, np.int64)
    unused = []
    for step in range(steps + 1):
        for s in np.flatnonzero(cur != FREE):
            if last[int(cur[s])] < step:
                cur[s] = FREE
        for i in born_at.get(step, ()):
            free = np.flatnonzero(cur == FREE)
            if free.size:
                cur[free[0]] = i
            else:
                unused.append(i)
        slot[step] = cur
    return SlotAssignment(slot, np.array(sorted(unused), np.int64))


@dataclass(frozen=True)
class SlotMeasurements:
    """The measurements of the slots, steps ``0..K``, ``N`` slots."""

    y: np.ndarray  # (K+1, N, 8) normalized image units, channels core.camera.CHANNELS; nan: no value
    measured: NDArray[np.bool_]  # (K+1, N) occupied and all 8 channels finite
    born: NDArray[np.bool_]  # (K+1, N) a new track entered the slot at this step
    body: np.ndarray  # (K+1, N, 3) true body point (target frame, m) of the slot's track; nan: unknown or empty
    sigma: np.ndarray  # (K+1, N, 2) the row's [position, velocity] sigma, normalized (sigma_px / f_px); nan: not given


def slot_measurements(tracks: pd.DataFrame, slots: SlotAssignment | np.ndarray, camera: PixelCamera) -> SlotMeasurements:
    """Measurement arrays of one trial's tracks in their slots (``slots``: :func:`assign_slots`'s, or its
    ``track`` array). Velocity columns absent from ``tracks`` are nan (so those slots are never ``measured``);
    ``body`` comes from ``body_x/y/z`` when present (the first finite value of each track)."""
    slot = slots.track if isinstance(slots, SlotAssignment) else np.asarray(slots, np.int64)
    K1, N = slot.shape
    y = np.full((K1, N, len(CHANNELS)), np.nan)
    body = np.full((K1, N, 3), np.nan)
    sigma = np.full((K1, N, 2), np.nan)
    kk, ss = np.nonzero(slot != FREE)
    occupied = pd.DataFrame({"step": kk, "slot": ss, "track_id": slot[kk, ss]})
    cols = [c for c in (*PIXEL_COLUMNS, "sigma_px", "sigma_pxps") if c in tracks]
    rows = occupied.merge(tracks[["step", "track_id", *cols]], on=["step", "track_id"], how="inner")
    k, s = rows["step"].to_numpy(dtype=np.int64), rows["slot"].to_numpy(dtype=np.int64)
    px = np.stack([rows[c].to_numpy(dtype=float) if c in rows else np.full(len(rows), np.nan) for c in PIXEL_COLUMNS],
                  axis=-1)  # fmt: skip
    y[k, s, 0], y[k, s, 1] = camera.normalized(px[:, 0], px[:, 1])
    y[k, s, 2], y[k, s, 3] = camera.normalized(px[:, 2], px[:, 3])
    y[k, s, 4:] = px[:, 4:] / camera.f_px  # velocities: d(col)/dt = f_px du/dt
    for j, c in enumerate(("sigma_px", "sigma_pxps")):
        if c in rows:
            sigma[k, s, j] = rows[c].to_numpy(dtype=float) / camera.f_px
    if {"body_x", "body_y", "body_z"} <= set(tracks.columns):
        b = tracks[["track_id", "body_x", "body_y", "body_z"]].dropna().groupby("track_id").first()
        have = occupied["track_id"].isin(b.index).to_numpy()
        body[kk[have], ss[have]] = b.loc[occupied["track_id"].to_numpy()[have]].to_numpy(dtype=float)
    measured = np.all(np.isfinite(y), axis=-1)
    prev = np.vstack([np.full((1, N), FREE, np.int64), slot[:-1]])
    born = (slot != FREE) & (slot != prev)
    return SlotMeasurements(y, measured, born, body, sigma)
