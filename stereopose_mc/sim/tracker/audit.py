"""The tracker truth audit: what each track really followed.

At a track's first step the renderer casts the ray through its right-image position
(renderer.cast) and takes the first body point hit, ``P`` in the target frame ``T``
(``nan`` if the ray misses the body: a track born on the background). At every later step
``k`` with the true pose ``(rho_k, D_k)``:

- ``err_r_px``, ``err_l_px``: distance between the tracked position and the true
  projection of ``P`` (``D_k P + rho_k`` projected by the point model's cameras);
- ``visible``: ``P`` is the first hit along both cameras' rays through its true
  projections (not occluded by the body, not on a face turned away);
- ``on_surface``: the ray through the tracked right-image position hits the same surface
  (scene.py: a box face, a panel side, the whole ellipsoid) as ``P`` was on.

Per track: ``lifetime`` (steps it was tracked), ``jumped`` (at some step the track was off
its surface or its point was hidden: it followed something else, e.g. a shadow edge, a
silhouette or an occluding edge). ``clean`` rows belong to tracks that never jumped.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..render.renderer import cast, project_px
from ..render.setup import ImageSetup

AUDIT_COLUMNS = {
    "body_x": "float64: the track's true body point P in T (m; nan: born off the body)",
    "body_y": "float64",
    "body_z": "float64",
    "err_r_px": "float64: |tracked - true projection of P|, right image (px)",
    "err_l_px": "float64: same, left image (px)",
    "visible": "bool: P is seen by both cameras at this step",
    "on_surface": "bool: the tracked right position lies on P's surface",
    "lifetime": "int64: steps the track lived",
    "jumped": "bool: the track left its surface or its point was hidden at some step",
    "clean": "bool: not jumped and born on the body",
}
VISIBLE_TOL = 1e-6  # relative to the body's size: a first hit this close to P is P


def audit(tracks: pd.DataFrame, setup: ImageSetup, poses) -> pd.DataFrame:
    """``tracks`` (klt.COLUMNS) with the :data:`AUDIT_COLUMNS`; ``poses[k] = (rho_k, D_k)``, the truth at step ``k``."""
    scene, rig = setup.scene, setup.rig
    out = tracks.copy()
    body = np.full((len(out), 3), np.nan)
    birth = out.groupby("track_id")["step"].transform("min").to_numpy()
    first = out["step"].to_numpy() == birth
    src_surface: dict[int, int] = {}
    for k in np.unique(out["step"].to_numpy()[first]):
        sel = np.flatnonzero(first & (out["step"].to_numpy() == k))
        h = cast(scene, rig, *poses[k], "right", out["col_r"].to_numpy()[sel], out["row_r"].to_numpy()[sel])
        body[sel] = h.point
        src_surface.update(zip(out["track_id"].to_numpy()[sel].tolist(), h.surface.tolist()))
    tid = out["track_id"].to_numpy()
    idx_first = pd.Series(np.flatnonzero(first), index=tid[first])
    body = body[idx_first.loc[tid].to_numpy()]
    err_r = np.full(len(out), np.nan)
    err_l = np.full(len(out), np.nan)
    visible = np.zeros(len(out), bool)
    on_surface = np.zeros(len(out), bool)
    tol = VISIBLE_TOL * scene.shape.extent
    steps = out["step"].to_numpy()
    px = {"right": out[["col_r", "row_r"]].to_numpy(), "left": out[["col_l", "row_l"]].to_numpy()}
    for k in np.unique(steps):
        sel = np.flatnonzero(steps == k)
        rho, D = poses[k]
        P = body[sel]
        p_L = P @ D.T + rho
        vis = np.isfinite(P[:, 0])
        for cam, err in (("right", err_r), ("left", err_l)):
            true_px = project_px(rig.camera, rig.baseline, p_L, cam)
            err[sel] = np.linalg.norm(px[cam][sel] - true_px, axis=1)
            ok = vis.copy()
            if ok.any():
                h = cast(scene, rig, rho, D, cam, true_px[ok, 0], true_px[ok, 1])
                ok[ok] = h.hit & (np.linalg.norm(np.nan_to_num(h.point) - P[ok], axis=1) < tol)
            vis &= ok
        visible[sel] = vis
        h = cast(scene, rig, rho, D, "right", px["right"][sel, 0], px["right"][sel, 1])
        on_surface[sel] = h.surface == np.array([src_surface[t] for t in tid[sel].tolist()])
    out["body_x"], out["body_y"], out["body_z"] = body.T
    out["err_r_px"], out["err_l_px"] = err_r, err_l
    out["visible"], out["on_surface"] = visible, on_surface
    g = out.groupby("track_id")
    out["lifetime"] = g["step"].transform("size").astype(np.int64)
    out["jumped"] = ~(out["visible"] & out["on_surface"]).groupby(out["track_id"]).transform("all")
    out["clean"] = ~out["jumped"] & np.isfinite(out["body_x"])
    return out


def summary(audited: pd.DataFrame) -> dict:
    """Headline numbers of an audited track table (each says what it counts)."""
    clean = audited[audited["clean"]]
    per_track = audited.groupby("track_id").agg(lifetime=("lifetime", "first"), jumped=("jumped", "first"))
    return {
        "tracks": int(len(per_track)),
        "tracks_jumped": int(per_track["jumped"].sum()),
        "rows": int(len(audited)),
        "clean_rows": int(len(clean)),
        "clean_median_err_r_px": float(clean["err_r_px"].median()) if len(clean) else float("nan"),
        "clean_p90_err_r_px": float(clean["err_r_px"].quantile(0.9)) if len(clean) else float("nan"),
        "clean_median_err_l_px": float(clean["err_l_px"].median()) if len(clean) else float("nan"),
        "median_lifetime_steps": float(per_track["lifetime"].median()),
    }
