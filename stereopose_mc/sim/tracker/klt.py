"""A stereo feature tracker on OpenCV: detection, stereo matching along the rows, temporal KLT.

Per step ``k`` with the rectified pair (right image ``R_k``, left image ``L_k``):

1. **Temporal tracking**, in each camera separately: pyramidal Lucas-Kanade (Bouguet 2000)
   from the previous image, then back (forward-backward check, Kalal et al. 2010: the round
   trip must close within ``fb_max_px``); the prediction is then refined by an affine match
   to the track's window from its detection frame (affine.py), which must correlate with it
   (NCC >= ``min_ncc``), stay within ``fb_max_px`` of the prediction and keep its scales in
   (0.5, 2). Matching to the detection window, not the last frame, keeps errors from adding
   up; a face turning away ends its tracks once its windows deform beyond recognition.
   A track also ends when its right and left rows disagree by more than ``row_max_px`` (the
   rig is rectified) or its right window fails the edge tests.
2. **Re-detection** when fewer than ``min_tracks`` remain: the detector (``gftt``: Shi-Tomasi,
   on the crop around the target, ``_gftt``; ``fast``, ``orb``, ``sift``) on ``R_k``, strongest
   first, at least ``min_distance_px`` from each other and from the live tracks, up to
   ``max_tracks``, candidates failing the edge tests dropped; each new track gets a new id (ids
   count up and are never reused).
3. **Stereo matching** of new tracks: KLT from ``R_k`` into ``L_k`` starting on the same row
   at the prior disparity (the median of the live tracks', or the pair's global shift by
   phase correlation), then back into ``R_k`` (left-right check, ``lr_max_px``), then the
   affine refinement of the right window in ``L_k`` (a slanted face looks sheared between
   the cameras); rejected when the refined windows correlate less than ``detect_ncc``, when
   the match leaves its row by more than ``row_max_px`` or straddles a depth edge (below).
4. **Edge tests** on the right image's window (``window_px`` square) around a feature:
   - *dark edge*: more than ``dark_max_fraction`` of the window below ``dark_dn`` (a shadow
     edge or the silhouette against a black sky: such features slide with the edge, not with
     the surface);
   - *aperture*: the window's structure tensor ``G = sum [Ix^2, IxIy; IxIy, Iy^2]`` has
     ``lambda_min / lambda_max < edge_ratio`` (a straight edge: KLT slides along it);
   - *depth edge* (at detection): on a plane the disparity of a rectified pair is affine in
     the image coordinates, so the disparities of small sub-windows at offsets
     ``(-3, -1, 1, 3) w / 8`` along the row (and, separately, down the column) lie on a line;
     a residual from the least-squares line above ``disparity_jump_px`` means the window
     straddles two depths (a step of ``D`` through the centre leaves residuals of ``0.3 D``).

Coordinates: OpenCV puts pixel centres at integers; the output uses the camera model's
continuous image coordinates (renderer.py: ``col = x_cv + 0.5``, ``row = y_cv + 0.5``).

Output (:func:`track_sequence`): a pandas DataFrame, one row per step and live track,
with the columns of :data:`COLUMNS`. Disparity keeps the point model's sign
(``d = col_l - col_r = -f_px b / y``, negative); image velocities are backward differences
``(p_k - p_{k-1}) / dt`` (nan at a track's first step); ``quality`` in ``[0, 1]`` is the
worse of the two cameras' affine-match NCCs (at detection: the stereo match's NCC).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import pandas as pd
from numpy.typing import NDArray

from . import affine

Array = NDArray[np.float64]
DETECTORS = ("gftt", "fast", "orb", "sift")
COLUMNS = {
    "step": "int64: time step k",
    "t_s": "float64: time (s)",
    "track_id": "int64: persistent track identity (never reused)",
    "age": "int64: steps since the track's detection (0 at detection)",
    "col_r": "float64: right-image column (px, camera-model convention)",
    "row_r": "float64: right-image row (px)",
    "col_l": "float64: left-image column (px)",
    "row_l": "float64: left-image row (px)",
    "disparity_px": "float64: col_l - col_r (px; negative, the point model's sign)",
    "dcol_r": "float64: right column velocity (px/s), backward difference; nan at detection",
    "drow_r": "float64: right row velocity (px/s)",
    "dcol_l": "float64: left column velocity (px/s)",
    "drow_l": "float64: left row velocity (px/s)",
    "fb_error_px": "float64: temporal forward-backward round-trip error, the worse camera (px; 0 at detection)",
    "lr_error_px": "float64: stereo left-right round-trip error at detection (px; nan afterwards)",
    "quality": "float64: NCC of the affine window matches, the worse camera (at detection: the stereo match), 0-1",
}


@dataclass(frozen=True)
class TrackerSettings:
    detector: str = "gftt"
    max_tracks: int = 150
    min_tracks: int = 80  # re-detect below this many live tracks
    min_distance_px: float = 8.0
    window_px: int = 21  # KLT window (odd)
    levels: int = 3  # pyramid levels above the image
    fb_max_px: float = 0.5
    lr_max_px: float = 0.5
    row_max_px: float = 0.5
    dark_dn: int = 8
    dark_max_fraction: float = 0.02
    edge_ratio: float = 0.05
    disparity_jump_px: float = 0.5
    min_ncc: float = 0.85  # affine match of a window to its detection window
    detect_ncc: float = 0.9  # stereo match (right window in the left image) a new track needs
    border_px: int = 16  # no features closer to the image border

    def __post_init__(self):
        if self.detector not in DETECTORS:
            raise ValueError(f"tracker detector: '{self.detector}' is not one of {', '.join(DETECTORS)}")


@dataclass(frozen=True)
class Side:
    """One camera's live tracks: positions (OpenCV coordinates), detection windows, affine warps."""

    p: Array = field(default_factory=lambda: np.zeros((0, 2)))
    T: Array = field(default_factory=lambda: np.zeros((0, 0)))  # (n, w*w) windows at detection
    SD: Array = field(default_factory=lambda: np.zeros((0, 0, 6)))  # their steepest-descent images
    A: Array = field(default_factory=lambda: np.zeros((0, 2, 2)))  # detection window -> current image
    image: NDArray | None = None

    def take(self, keep: NDArray[np.bool_]) -> Side:
        return Side(self.p[keep], self.T[keep], self.SD[keep], self.A[keep], self.image)

    def add(self, image: NDArray, p: Array, w: int) -> Side:
        T, SD = affine.templates(image, p, w)
        return Side(np.r_[self.p, p], np.concatenate([self.T.reshape(-1, w * w), T]),
                    np.concatenate([self.SD.reshape(-1, w * w, 6), SD]),
                    np.concatenate([self.A, np.repeat(np.eye(2)[None], len(p), axis=0)]), self.image)  # fmt: skip


@dataclass(frozen=True)
class TrackerState:
    ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    age: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    right: Side = Side()
    left: Side = Side()
    next_id: int = 0


def _lk(settings: TrackerSettings, window: int | None = None, levels: int | None = None) -> dict:
    w = window or settings.window_px
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 0.003)
    return dict(winSize=(w, w), maxLevel=settings.levels if levels is None else levels, criteria=crit)


def klt(a: NDArray, b: NDArray, p: Array, guess: Array, settings: TrackerSettings, **kw) -> tuple[Array, NDArray]:
    """Pyramidal KLT of points ``p (n, 2)`` from image ``a`` to ``b`` starting at ``guess``; (positions, ok)."""
    if len(p) == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    q, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p.astype(np.float32).reshape(-1, 1, 2),
                                        guess.astype(np.float32).reshape(-1, 1, 2),
                                        flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **_lk(settings, **kw))  # fmt: skip
    return q.reshape(-1, 2).astype(float), st.ravel().astype(bool)


GFTT = dict(qualityLevel=0.01, minDistance=1, blockSize=7)  # Shi-Tomasi's settings (Sobel aperture 3)
# The crop around a frame's target (``_gftt``): the pixels above NOISE_DN (the black sky's read noise is 0-1 DN) with
# CROP_MARGIN pixels around them (the response's reach, Sobel's 1 + the block's 3, twice); its columns start on a
# multiple of CROP_ALIGN so that each pixel takes the same SIMD lane of OpenCV's row loops as in the whole frame.
NOISE_DN, CROP_MARGIN, CROP_ALIGN = 1, 8, 64


def noise_response(level: float, block: int = GFTT["blockSize"]) -> float:
    """An upper bound of OpenCV's Shi-Tomasi response (``cv2.cornerMinEigenVal``, Sobel aperture 3) at a pixel whose
    ``block + 2`` square window holds values in ``[0, level]``: each Sobel derivative is at most ``4 level`` times
    OpenCV's scale ``1 / (4 block 255)``, the smaller eigenvalue at most the block's sum of its squares."""
    return block * block * (4.0 * level / (4 * block * 255.0)) ** 2


def _support(image: NDArray, level: float) -> tuple[int, int, int, int] | None:
    """``(r0, r1, c0, c1)``: the rows and columns of ``image``'s pixels above ``level`` with ``CROP_MARGIN`` around
    them (the columns from a multiple of ``CROP_ALIGN``), clipped to the image; None if there is none."""
    _, above = cv2.threshold(image, level, 255, cv2.THRESH_BINARY)
    x, y, w, h = cv2.boundingRect(above)
    if w == 0 or h == 0:
        return None
    H, W = image.shape
    c0 = max(0, (x - CROP_MARGIN) // CROP_ALIGN * CROP_ALIGN)
    c1 = min(W, -(-(x + w + CROP_MARGIN) // CROP_ALIGN) * CROP_ALIGN)
    return max(0, y - CROP_MARGIN), min(H, y + h + CROP_MARGIN), c0, c1


def _gftt(image: NDArray, mask: NDArray | None, n: int) -> Array:
    """Shi-Tomasi corners (``cv2.goodFeaturesToTrack`` with ``GFTT``; ``n = 0``: all), strongest first.

    A rendered frame is mostly black sky (the bundled target is ~100 px across in a 1024 px frame): on an 8-bit
    image the detector runs on the crop around the pixels above the sky's noise (``_support``), which gives the
    same corners as the whole image whenever the noise cannot reach the detector's threshold (``qualityLevel``
    times the strongest response), checked on the crop's own strongest response against ``noise_response``
    (with a factor 2 of room): then every response outside the crop, and near its edges, is at most the noise's
    and is cut by the threshold; those inside are the same numbers; the strongest is inside; the corners keep
    their order (the sort breaks ties by position, which the crop keeps in order). Otherwise (a faint target, a
    noisy frame) the whole image. On the bundled frames (1024 px) 20 ms -> 1.3 ms per detection.
    """
    if image.dtype == np.uint8 and image.ndim == 2:
        box = _support(image, NOISE_DN)
        if box is not None:
            r0, r1, c0, c1 = box
            sub = np.ascontiguousarray(image[r0:r1, c0:c1])
            m = None if mask is None else np.ascontiguousarray(mask[r0:r1, c0:c1])
            eig = cv2.cornerMinEigenVal(sub, GFTT["blockSize"], 3)
            top = float(eig.max()) if m is None else cv2.minMaxLoc(eig, m)[1]
            if 2.0 * noise_response(NOISE_DN) <= GFTT["qualityLevel"] * top:
                return _corners(sub, m, n) + [c0, r0]
    return _corners(image, mask, n)


def _corners(image: NDArray, mask: NDArray | None, n: int) -> Array:
    """``cv2.goodFeaturesToTrack`` with ``GFTT`` as ``(n, 2)`` floats (OpenCV coordinates of ``image``)."""
    c = cv2.goodFeaturesToTrack(image, maxCorners=n, mask=mask, **GFTT)
    return np.zeros((0, 2)) if c is None else c.reshape(-1, 2).astype(float)


def keypoints(image: NDArray, detector: str, mask: NDArray | None = None, n: int = 0) -> tuple[Array, Array]:
    """All detections ``(n, 2)`` (OpenCV coordinates) and their responses, strongest first."""
    if detector == "gftt":
        pts = _gftt(image, mask, n)
        return pts, -np.arange(len(pts), dtype=float)  # already strongest first
    det = {"fast": lambda: cv2.FastFeatureDetector_create(threshold=20),
           "orb": lambda: cv2.ORB_create(nfeatures=n or 5000),
           "sift": lambda: cv2.SIFT_create(nfeatures=n)}[detector]()  # fmt: skip
    kp = det.detect(image, mask)
    pts = np.array([k.pt for k in kp], dtype=float).reshape(-1, 2)
    resp = np.array([k.response for k in kp], dtype=float)
    order = np.argsort(-resp, kind="stable")
    return pts[order], resp[order]


def select(pts: Array, taken: Array, shape: tuple[int, int], settings: TrackerSettings, n: int) -> Array:
    """Up to ``n`` of ``pts`` (strongest first) at least ``min_distance_px`` from each other and ``taken``."""
    r = int(np.ceil(settings.min_distance_px))
    free = np.full(shape, 255, np.uint8)
    for x, y in taken:
        cv2.circle(free, (int(round(x)), int(round(y))), r, 0, -1)
    out = []
    for x, y in pts:
        if len(out) >= n:
            break
        if free[int(round(y)), int(round(x))]:
            out.append((x, y))
            cv2.circle(free, (int(round(x)), int(round(y))), r, 0, -1)
    return np.array(out, dtype=float).reshape(-1, 2)


def _windows(image: NDArray, p: Array, w: int) -> NDArray[np.float32]:
    return np.stack([cv2.getRectSubPix(image, (w, w), (float(x), float(y))) for x, y in p]).astype(np.float32) \
        if len(p) else np.zeros((0, w, w), np.float32)


def edge_free(image: NDArray, p: Array, settings: TrackerSettings) -> NDArray[np.bool_]:
    """The dark-edge and aperture tests of the windows around ``p`` (True: keep)."""
    w = settings.window_px
    win = _windows(image, p, w)
    dark = (win < settings.dark_dn).mean(axis=(1, 2)) <= settings.dark_max_fraction
    gx = np.diff(win, axis=2)[:, :-1, :]
    gy = np.diff(win, axis=1)[:, :, :-1]
    a, b, c = (gx * gx).sum((1, 2)), (gx * gy).sum((1, 2)), (gy * gy).sum((1, 2))
    root = np.sqrt(0.25 * (a - c) ** 2 + b * b)
    lmax, lmin = 0.5 * (a + c) + root, 0.5 * (a + c) - root
    textured = lmin > settings.edge_ratio * np.maximum(lmax, 1e-12)
    return dark & textured


def stereo(right: NDArray, left: NDArray, p_r: Array, d0: Array, settings: TrackerSettings):
    """Left positions, left-right error, keep-mask and window NCC of right points ``p_r`` (prior disparities ``d0``)."""
    guess = p_r + np.c_[d0, np.zeros_like(d0)]
    p_l, ok1 = klt(right, left, p_r, guess, settings)
    back, ok2 = klt(left, right, p_l, p_r, settings)
    lr = np.linalg.norm(back - p_r, axis=1)
    ok = ok1 & ok2 & (lr <= settings.lr_max_px) & (np.abs(p_l[:, 1] - p_r[:, 1]) <= settings.row_max_px)
    # depth edge: the disparities of sub-windows along the row and the column must lie on lines
    q = settings.window_px / 8.0
    x = np.array([-3.0, -1.0, 1.0, 3.0])
    offs = np.r_[np.c_[q * x, np.zeros(4)], np.c_[np.zeros(4), q * x]]  # (8, 2): 4 along the row, 4 down
    sub = (p_r[:, None, :] + offs).reshape(-1, 2)
    d = (p_l - p_r)[:, 0]
    sg = sub + np.c_[np.repeat(d, len(offs)), np.zeros(len(sub))]
    ps, oks = klt(right, left, sub, sg, settings, window=max(7, settings.window_px // 3 | 1), levels=1)
    ds = (ps - sub)[:, 0].reshape(-1, 2, 4)
    oks = oks.reshape(-1, 8).all(axis=1) & (np.abs((ps - sub)[:, 1]).reshape(-1, 8) <= 1.0).all(axis=1)
    ok &= oks & (line_residual(ds, x).max(axis=(1, 2)) <= settings.disparity_jump_px)
    # the left window is the right one scaled and sheared by the surface's slant: affine refinement
    w = settings.window_px
    T, SD = affine.templates(right, p_r, w)
    _, p_l2, q = affine.refine(left, T, SD, np.repeat(np.eye(2)[None], len(p_r), axis=0), p_l, w)
    ok &= (np.linalg.norm(p_l2 - p_l, axis=1) <= settings.lr_max_px) & (q >= settings.min_ncc)
    ok &= np.abs(p_l2[:, 1] - p_r[:, 1]) <= settings.row_max_px
    return p_l2, lr, ok, q


def line_residual(y: Array, x: Array) -> Array:
    """Residuals of the least-squares lines through ``(x, y[..., :])`` (``x`` centred: ``sum x = 0``)."""
    slope = (y * x).sum(-1, keepdims=True) / (x * x).sum()
    return np.abs(y - y.mean(-1, keepdims=True) - slope * x)


def global_disparity(right: NDArray, left: NDArray) -> float:
    """The pair's overall horizontal shift ``col_l - col_r`` by phase correlation."""
    a, b = right.astype(np.float32), left.astype(np.float32)
    win = cv2.createHanningWindow(a.shape[::-1], cv2.CV_32F)
    (dx, _), _ = cv2.phaseCorrelate(a, b, win)
    return float(dx)


def inside(p: Array, shape: tuple[int, int], border: int) -> NDArray[np.bool_]:
    H, W = shape
    return (p[:, 0] >= border) & (p[:, 0] < W - border) & (p[:, 1] >= border) & (p[:, 1] < H - border)


def temporal(side: Side, image: NDArray, settings: TrackerSettings):
    """Track one camera's windows into its new image: KLT from the previous image with the forward-backward
    check, then the affine match to the detection window. Returns the moved side, fb error, NCC and keep-mask."""
    pred, ok = klt(side.image, image, side.p, side.p, settings)
    back, ok2 = klt(image, side.image, pred, side.p, settings)
    fb = np.linalg.norm(back - side.p, axis=1)
    A, t, q = affine.refine(image, side.T, side.SD, side.A, pred, settings.window_px)
    sv = np.linalg.svd(A, compute_uv=False)
    keep = (ok & ok2 & (fb <= settings.fb_max_px) & (q >= settings.min_ncc) & inside(t, image.shape, settings.border_px)
            & (np.linalg.norm(t - pred, axis=1) <= settings.fb_max_px) & (sv.min(1) > 0.5) & (sv.max(1) < 2.0))
    return Side(t, side.T, side.SD, A, image), fb, q, keep


def step(state: TrackerState, right: NDArray, left: NDArray, settings: TrackerSettings):
    """One step: returns the new state and the live tracks' arrays
    ``(ids, age, p_r, p_l, fb, lr, quality)`` in OpenCV coordinates."""
    shape, w = right.shape, settings.window_px
    ids, age, R, L = state.ids, state.age, state.right, state.left
    n = len(ids)
    fb, lr, quality = np.zeros(n), np.full(n, np.nan), np.ones(n)
    if n:
        R, fb_r, q_r, ok_r = temporal(R, right, settings)
        L, fb_l, q_l, ok_l = temporal(L, left, settings)
        keep = ok_r & ok_l & (np.abs(L.p[:, 1] - R.p[:, 1]) <= settings.row_max_px) & edge_free(right, R.p, settings)
        fb, quality = np.maximum(fb_r, fb_l), np.minimum(q_r, q_l)
        ids, age, fb, lr, quality = ids[keep], age[keep] + 1, fb[keep], lr[keep], quality[keep]
        R, L = R.take(keep), L.take(keep)
    R, L = replace(R, image=right), replace(L, image=left)
    next_id = state.next_id
    if len(ids) < settings.min_tracks:
        mask = np.zeros(shape, np.uint8)
        b = settings.border_px
        mask[b:-b, b:-b] = 255
        cand, _ = keypoints(right, settings.detector, mask)
        cand = cand[edge_free(right, cand, settings)] if len(cand) else cand
        add = select(cand, R.p, shape, settings, settings.max_tracks - len(ids))
        d = (L.p - R.p)[:, 0]
        prior = float(np.median(d)) if len(d) else global_disparity(right, left)
        p_l, lr_new, ok, q = stereo(right, left, add, np.full(len(add), prior), settings)
        ok &= inside(p_l, shape, settings.border_px) & (q >= settings.detect_ncc)
        add, p_l, lr_new, q = add[ok], p_l[ok], lr_new[ok], q[ok]
        ids = np.r_[ids, next_id + np.arange(len(add))]
        next_id += len(add)
        R, L = R.add(right, add, w), L.add(left, p_l, w)
        age, fb = np.r_[age, np.zeros(len(add), np.int64)], np.r_[fb, np.zeros(len(add))]
        lr, quality = np.r_[lr, lr_new], np.r_[quality, q]
    new_state = TrackerState(ids, age, R, L, next_id)
    return new_state, (ids, age, R.p, L.p, fb, lr, np.clip(quality, 0.0, 1.0))


def track_sequence(frames, dt: float, settings: TrackerSettings = TrackerSettings(), t0: float = 0.0) -> pd.DataFrame:
    """Track an iterable of ``(right, left)`` uint8 image pairs (step ``k`` at ``t0 + k dt``); the table of
    :data:`COLUMNS`."""
    state = TrackerState()
    rows = []
    last: dict[int, tuple[Array, Array]] = {}
    for k, (right, left) in enumerate(frames):
        state, (ids, age, p_r, p_l, fb, lr, quality) = step(state, right, left, settings)
        vel = np.full((len(ids), 4), np.nan)
        for i, tid in enumerate(ids.tolist()):
            if tid in last and age[i] > 0:
                vel[i] = np.r_[p_r[i] - last[tid][0], p_l[i] - last[tid][1]] / dt
        last = {tid: (p_r[i], p_l[i]) for i, tid in enumerate(ids.tolist())}
        rows.append(pd.DataFrame({
            "step": np.full(len(ids), k, np.int64), "t_s": t0 + k * dt, "track_id": ids.astype(np.int64),
            "age": age.astype(np.int64), "col_r": p_r[:, 0] + 0.5, "row_r": p_r[:, 1] + 0.5,
            "col_l": p_l[:, 0] + 0.5, "row_l": p_l[:, 1] + 0.5, "disparity_px": p_l[:, 0] - p_r[:, 0],
            "dcol_r": vel[:, 0], "drow_r": vel[:, 1], "dcol_l": vel[:, 2], "drow_l": vel[:, 3],
            "fb_error_px": fb, "lr_error_px": lr, "quality": quality,
        }))  # fmt: skip
    out = pd.concat(rows, ignore_index=True) if rows else pd.DataFrame(columns=list(COLUMNS))
    return out[list(COLUMNS)]
