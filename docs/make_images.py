"""Regenerate docs/images.md's measured blocks: the detector comparison and the example frames.

    .venv/bin/python docs/make_images.py              # about a minute on one core
    .venv/bin/python docs/make_images.py --steps 30   # a quicker, shorter sequence

The bundled example (configs/mission-realistic.yaml: a 2 x 1.5 x 3 m box 62 m ahead, 1024 px,
40 deg field of view) with two solar-panel wings is rendered along its truth, once as the
scenario has it and once with the relative position scaled to 20 m (a closer inspection
pass, same attitude). Per geometry and detector (the thesis's Figs. 3.8-3.9 compare the
number of features and the time per detector): the keypoints the detector finds in the
right image, its time per image, and what the tracker makes of them over the sequence (the
truth audit's errors of clean tracks). Example frames with the tracks drawn go to
docs/images/.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from docgen import splice

from stereopose_mc.config import load_scenario
from stereopose_mc.config.resolve import setup_of
from stereopose_mc.sim.render import renderer as rr, sensor as ss
from stereopose_mc.sim.render.scene import Panels
from stereopose_mc.sim.render.setup import ImageSetup, image_setup
from stereopose_mc.sim import tracks_file
from stereopose_mc.sim.tracker import audit, klt
from stereopose_mc.sim.truth import simulate_truth

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "mission-realistic.yaml"
DOC = ROOT / "docs" / "images.md"
FIGS = ROOT / "docs" / "images"
PANELS = Panels(span_m=3.0, width_m=1.0, axis=0, normal_axis=1)  # wings along x, cells toward -y (the cameras)
CLOSE_RANGE_M = 20.0
SETTINGS = klt.TrackerSettings(window_px=15, min_distance_px=6.0, max_tracks=150, min_tracks=60)
SEED = 7  # sensor noise of the sequences


def sequences(steps: int):
    """``(label, setup, poses, frames)`` of the two geometries; frames are noisy 8-bit stereo pairs."""
    s = load_scenario(CONFIG)
    truth = simulate_truth(setup_of(s))
    setup = image_setup(s, PANELS)
    poses = [rr.pose_of(x) for x in truth.x[: steps + 1]]
    dt = float(truth.t[1] - truth.t[0])
    out = []
    for label, scale in (("scenario", 1.0), (f"{CLOSE_RANGE_M:g} m", None)):
        pp = poses if scale else [(rho * CLOSE_RANGE_M / np.linalg.norm(rho), D) for rho, D in poses]
        rng = np.random.default_rng(SEED)
        t0 = time.perf_counter()
        frames = []
        for rho, D in pp:
            f = rr.render_stereo(setup.scene, setup.rig, rho, D, setup.sun_L)
            frames.append((ss.expose(f.right.radiance, ss.SensorModel(), rng),
                           ss.expose(f.left.radiance, ss.SensorModel(), rng)))  # fmt: skip
        render_s = (time.perf_counter() - t0) / (2 * len(pp))
        rng_m = float(np.median([np.linalg.norm(rho) for rho, _ in pp]))
        out.append((label, setup, pp, frames, dt, render_s, rng_m))
    return out


def detector_rows(label, frames, setup: ImageSetup, poses, dt):
    rows, tables = [], {}
    for det in klt.DETECTORS:
        counts, times = [], []
        for right, _ in frames[:: max(1, len(frames) // 10)]:
            t0 = time.perf_counter()
            pts, _ = klt.keypoints(right, det)
            times.append(time.perf_counter() - t0)
            counts.append(len(pts))
        t0 = time.perf_counter()
        tracks = klt.track_sequence(frames, dt, klt.TrackerSettings(**{**SETTINGS.__dict__, "detector": det}))
        track_s = (time.perf_counter() - t0) / len(frames)
        a = audit.audit(tracks, setup, poses)
        sm = audit.summary(a)
        tables[det] = a
        rows.append({
            "geometry": label, "detector": det, "keypoints per image (median)": int(np.median(counts)),
            "detect ms per image": round(1e3 * float(np.median(times)), 1),
            "live tracks per step (median)": int(a.groupby("step").size().median()),
            "tracks": sm["tracks"], "jumped": sm["tracks_jumped"],
            "clean median error R/L px": f"{sm['clean_median_err_r_px']:.3f} / {sm['clean_median_err_l_px']:.3f}",
            "clean p90 R px": f"{sm['clean_p90_err_r_px']:.3f}",
            "median lifetime steps": f"{sm['median_lifetime_steps']:.0f}",
            "tracker ms per step": round(1e3 * track_s, 1),
        })  # fmt: skip
    return rows, tables


def crop_box(setup: ImageSetup, poses, margin: int = 12) -> tuple[slice, slice]:
    """The right image's region the target covers over the sequence, with a margin."""
    wins = [rr.footprint_window(setup.scene, setup.rig, rho, D, "right") for rho, D in poses]
    cam = setup.rig.camera
    r0, r1 = min(w[0].start for w in wins) - margin, max(w[0].stop for w in wins) + margin
    c0, c1 = min(w[1].start for w in wins) - margin, max(w[1].stop for w in wins) + margin
    return slice(max(0, r0), min(cam.height, r1)), slice(max(0, c0), min(cam.width, c1))


def draw(image, a: pd.DataFrame, k: int, box, scale: int) -> np.ndarray:
    """The right image at step ``k`` with each live track's last 10 positions (green: clean, red: jumped)."""
    rows, cols = box
    img = cv2.cvtColor(image[rows, cols], cv2.COLOR_GRAY2BGR)
    img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    live = a[(a["step"] <= k) & (a["step"] > k - 10)]
    for tid, g in live.groupby("track_id"):
        if g["step"].max() != k:
            continue
        pts = np.c_[(g["col_r"] - cols.start) * scale, (g["row_r"] - rows.start) * scale]
        colour = (60, 220, 60) if bool(g["clean"].iloc[0]) else (40, 40, 230)
        cv2.polylines(img, [np.round(pts).astype(np.int32)], False, colour, 1, cv2.LINE_AA)
        cv2.circle(img, tuple(np.round(pts[-1]).astype(int)), 2, colour, -1, cv2.LINE_AA)
    return img


def markdown(df: pd.DataFrame) -> str:
    cols = list(df.columns)
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    out += ["| " + " | ".join(str(v) for v in r) + " |" for r in df.itertuples(index=False)]
    return "\n".join(out)


def schema_table(columns: dict) -> str:
    rows = [(k, *v.split(": ", 1)) if ": " in v else (k, v, "") for k, v in columns.items()]
    return "\n".join(["| column | type | meaning |", "|---|---|---|"] + [f"| `{a}` | {b} | {c} |" for a, b, c in rows])


def schemas(text: str) -> str:
    """``text`` with the generated schema tables: the tracker's, the audit's, a track file's, a truth file's."""
    for name, cols in (("tracks-schema", klt.COLUMNS), ("audit-schema", audit.AUDIT_COLUMNS),
                       ("tracks-file-schema", tracks_file.TRACK_FILE_COLUMNS),
                       ("truth-file-schema", tracks_file.TRUTH_FILE_COLUMNS)):  # fmt: skip
        text = splice(text, name, schema_table(cols), DOC)
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=100, help="steps of the truth to render (default 100)")
    ap.add_argument("--schemas-only", action="store_true", help="only the schema tables (no rendering, seconds)")
    args = ap.parse_args(argv)
    if args.schemas_only:
        DOC.write_text(schemas(DOC.read_text(encoding="utf-8")), encoding="utf-8")
        print(f"-> {DOC} (schema tables)")
        return 0
    t_start = time.perf_counter()
    FIGS.mkdir(parents=True, exist_ok=True)
    rows, frames_md = [], []
    for i, (label, setup, poses, frames, dt, render_s, rng_m) in enumerate(sequences(args.steps)):
        r, tables = detector_rows(label, frames, setup, poses, dt)
        rows += r
        a = tables["gftt"]
        box = crop_box(setup, poses)
        scale = 2 if i == 0 else 1
        for k in (0, len(frames) - 1):
            name = f"tracks-{'far' if i == 0 else 'near'}-{k:03d}.png"
            cv2.imwrite(str(FIGS / name), draw(frames[k][0], a, k, box, scale))
            frames_md.append(f"![{label}, step {k}](images/{name})")
        frames_md.append(f"\n*{label}: range {rng_m:.1f} m, right image cropped around the target"
                         f"{' and enlarged 2x' if scale == 2 else ''}, steps 0 and {len(frames) - 1}; "
                         f"rendering {1e3 * render_s:.0f} ms per 1024 px image.*\n")  # fmt: skip
    table = pd.DataFrame(rows)
    text = DOC.read_text(encoding="utf-8")
    text = splice(text, "detectors", markdown(table), DOC)
    text = splice(text, "frames", "\n".join(frames_md), DOC)
    text = schemas(text)
    text = splice(text, "run", f"Last run: {args.steps} steps, {time.perf_counter() - t_start:.0f} s of wall time.", DOC)
    DOC.write_text(text, encoding="utf-8")
    print(markdown(table))
    print(f"-> {DOC}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
