"""Measure the image source's errors on a scenario, for the filter's R (configs/caseB-images.yaml's comment).

    .venv/bin/python docs/measure_tracker_noise.py                              # configs/caseB-images.yaml, 4 trials
    .venv/bin/python docs/measure_tracker_noise.py configs/X.yaml --trials 8

Runs sim/images.py ``campaign_tracks`` (render once, per-trial noise, tracker, audit) and compares the
clean tracks (the audit's ``clean``: born on the body, never off its surface or hidden) with the truth's
exact measurement of each track's true body point, the point model's ``core.camera.h_features``: image
positions in both cameras and the instantaneous image velocities the filter's model predicts (the
tracker's velocities are backward differences, so their error includes that difference). Prints the
per-channel median absolute, RMS and p90 errors in px and px/s, the track counts per step and the times.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

from stereopose_mc.config import load_scenario
from stereopose_mc.config.resolve import setup_of
from stereopose_mc.config.sensor import pixel_camera_of
from stereopose_mc.core import camera, state as st
from stereopose_mc.sim import images
from stereopose_mc.sim.render import renderer as rr
from stereopose_mc.sim.slots import PIXEL_COLUMNS, assign_slots
from stereopose_mc.sim.truth import simulate_truth

ROOT = Path(__file__).resolve().parents[1]


def errors_px(tracks, truth, setup, cam):
    """Tracked minus true, ``(rows, 8)`` in px and px/s (channel order core.camera.CHANNELS), clean rows."""
    c = tracks[tracks["clean"]]
    x = truth.x[c["step"].to_numpy()]
    x1 = np.concatenate([x[:, : st.QUAT.stop], c[["body_x", "body_y", "body_z"]].to_numpy(), x[:, -2:]], axis=1)
    y = camera.h_features(x1, setup.baseline)[:, 0]  # normalized
    true_px = np.column_stack([*cam.pixels(y[:, 0], y[:, 1]), *cam.pixels(y[:, 2], y[:, 3]), cam.f_px * y[:, 4:]])
    return c[list(PIXEL_COLUMNS)].to_numpy() - true_px


def slotted(tracks, n_slots: int, steps: int) -> np.ndarray:
    """Rows of one trial's tracks whose track holds a slot at that step (sim/slots.py)."""
    slot = assign_slots(tracks, n_slots, steps).track
    held = set(zip(*(a.tolist() for a in np.nonzero(slot >= 0))))
    held = {(k, int(slot[k, i])) for k, i in held}
    return np.array([(k, t) in held for k, t in zip(tracks["step"].tolist(), tracks["track_id"].tolist())], bool)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", nargs="?", default=str(ROOT / "configs" / "caseB-images.yaml"))
    ap.add_argument("--trials", type=int, default=4)
    args = ap.parse_args(argv)
    s = load_scenario(args.config)
    setup = setup_of(s)
    truth = simulate_truth(setup)
    cam = pixel_camera_of(s)
    cfg = images.image_config(s)
    img = images.image_setup(s, cfg.panels)
    poses = [rr.pose_of(x) for x in truth.x]
    t0 = time.perf_counter()
    images.render_radiance(img, poses, cfg.render)
    render_s = time.perf_counter() - t0
    per_trial = []
    tables = []
    for j in range(args.trials):
        t0 = time.perf_counter()
        tables.append(images.campaign_tracks(s, setup, truth, [j], s.seed))  # cached radiance after the first
        per_trial.append(time.perf_counter() - t0)
    tr = pd.concat(tables, ignore_index=True)
    counts = tr.groupby(["trial", "step"]).size()
    per_track = tr.groupby(["trial", "track_id"]).agg(clean=("clean", "first"), life=("lifetime", "first"))
    in_slot = np.concatenate([slotted(g, s.target.feature_slots, setup.steps) for _, g in tr.groupby("trial", sort=False)])
    after = tr["age"].to_numpy() > 0  # at detection the audit's true point is the tracked one: error 0 by definition
    in_slot = in_slot[after & tr["clean"].to_numpy()]
    tr = tr[after]
    err = errors_px(tr, truth, setup, cam)
    print(f"{args.config}: {args.trials} trials, {setup.steps + 1} steps, {cam.width} px")
    print(f"render (both cameras, all steps, uncached): {render_s:.1f} s = {1e3 * render_s / (2 * len(poses)):.0f} ms "
          f"per image")
    print(f"per trial (cached radiance: noise + tracker + audit): {np.round(per_trial, 1).tolist()} s "
          f"(the first includes rendering when the cache was empty)")
    print(f"live tracks per step: median {counts.median():.0f}, p10 {counts.quantile(0.1):.0f}, min {counts.min()}, "
          f"max {counts.max()} ({len(counts)} trial-steps)")
    print(f"tracks: {len(per_track)}, clean {per_track['clean'].mean():.1%}, median lifetime {per_track['life'].median():.0f}")
    print(f"clean rows after detection: {int(tr['clean'].sum())} of {len(tr)}")
    for label, e_all in (("all clean rows after detection", err), (f"rows of the tracks in the "
                         f"{s.target.feature_slots} slots (sim/slots.py)", err[in_slot])):  # fmt: skip
        print(f"\n{label}: 1.4826 MAD is the Gaussian core's sigma; RMS includes the tails the gate sees")
        print("| channel | rows | median abs | 1.4826 MAD | RMS | p90 abs | p99 abs |")
        print("|---|---|---|---|---|---|---|")
        for j, name in enumerate(PIXEL_COLUMNS):
            e = e_all[:, j][np.isfinite(e_all[:, j])]
            unit = "px/s" if name.startswith("d") else "px"
            mad = 1.4826 * np.median(np.abs(e - np.median(e)))
            print(f"| {name} ({unit}) | {e.size} | {np.median(np.abs(e)):.3f} | {mad:.3f} | {np.sqrt(np.mean(e**2)):.3f} "
                  f"| {np.quantile(np.abs(e), 0.9):.3f} | {np.quantile(np.abs(e), 0.99):.3f} |")
        pos, vel = e_all[:, :4], e_all[:, 4:]
        pos, vel = pos[np.isfinite(pos)], vel[np.isfinite(vel)]
        print(f"positions: 1.4826 MAD {1.4826 * np.median(np.abs(pos - np.median(pos))):.3f} px, RMS "
              f"{np.sqrt(np.mean(pos**2)):.3f} px; velocities: 1.4826 MAD "
              f"{1.4826 * np.median(np.abs(vel - np.median(vel))):.3f} px/s, RMS {np.sqrt(np.mean(vel**2)):.3f} px/s")
    # what a track does after its detection (clean tracks): the jump to its first tracked position, and its drift
    # from there to its last row (right column; the filter births a slot at the first tracked row, mc/tracked.py)
    c = tr[tr["clean"].to_numpy()].assign(e=err[:, 0])
    g = c.sort_values("step").groupby(["trial", "track_id"])["e"]
    jump = g.first()
    drift = (g.last() - g.first())[g.size() >= 10]
    print(f"\nclean tracks, right column: jump from the detection to the first tracked frame RMS {np.sqrt(np.mean(jump**2)):.3f} px "
          f"({jump.size} tracks); drift from there to the last row RMS {np.sqrt(np.mean(drift**2)):.3f} px, median |drift| "
          f"{np.median(np.abs(drift)):.3f} px ({drift.size} tracks of >= 10 rows)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
