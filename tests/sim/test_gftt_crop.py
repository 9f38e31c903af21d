"""The tracker's Shi-Tomasi detection on the crop around a frame's target (sim/tracker/klt.py, ``_gftt``): the same
corners, in the same order, as ``cv2.goodFeaturesToTrack`` on the whole frame."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from stereopose_mc.sim.tracker import klt


def whole(image: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    c = cv2.goodFeaturesToTrack(image, maxCorners=0, mask=mask, **klt.GFTT)
    return np.zeros((0, 2)) if c is None else c.reshape(-1, 2).astype(float)


def frame(rng, shape=(480, 640), box=(200, 300, 260, 420), contrast=120.0, noise_pixels=60, noise_dn=1):
    """A black frame with a textured target in ``box`` (rows r0:r1, columns c0:c1) and ``noise_pixels`` scattered
    pixels of ``noise_dn`` (the sky's read noise)."""
    img = np.zeros(shape)
    r0, r1, c0, c1 = box
    tex = gaussian_filter(rng.normal(size=(r1 - r0, c1 - c0)), 1.5)
    img[r0:r1, c0:c1] = 20.0 + contrast * (tex - tex.min()) / np.ptp(tex)
    out = np.clip(np.round(img), 0, 255).astype(np.uint8)
    idx = rng.integers(0, out.size, noise_pixels)
    out.ravel()[idx] = np.maximum(out.ravel()[idx], noise_dn)
    return out


def spied(monkeypatch) -> list:
    """The shapes of the images ``cv2.goodFeaturesToTrack`` is called on (from now on)."""
    seen = []
    real = cv2.goodFeaturesToTrack

    def spy(image, **kw):
        seen.append(image.shape)
        return real(image, **kw)

    monkeypatch.setattr(klt.cv2, "goodFeaturesToTrack", spy)
    return seen


def border_mask(shape, b=10):
    m = np.zeros(shape, np.uint8)
    m[b:-b, b:-b] = 255
    return m


@pytest.mark.parametrize("seed", range(6))
def test_the_crop_finds_the_corners_of_the_whole_frame_in_their_order(seed):
    rng = np.random.default_rng(seed)
    img = frame(rng, box=(int(rng.integers(20, 200)), 330, int(rng.integers(5, 250)), 501))
    for mask in (None, border_mask(img.shape)):
        ref = whole(img, mask)
        assert len(ref) > 20
        assert np.array_equal(klt.keypoints(img, "gftt", mask)[0], ref)


def test_the_crop_runs_on_a_small_part_of_a_black_frame(monkeypatch):
    """On a frame whose target covers a small part, the detector sees the crop (not the frame)."""
    rng = np.random.default_rng(3)
    img = frame(rng, shape=(1024, 1024), box=(700, 790, 670, 815))
    seen = spied(monkeypatch)
    pts = klt.keypoints(img, "gftt", border_mask(img.shape))[0]
    monkeypatch.undo()
    assert np.array_equal(pts, whole(img, border_mask(img.shape)))
    (h, w), = seen
    assert h == 90 + 2 * klt.CROP_MARGIN and w % klt.CROP_ALIGN == 0 and w < 300


@pytest.mark.parametrize("case", ["edge", "black", "faint", "noisy"])
def test_frames_the_crop_cannot_shortcut_give_the_whole_frames_corners(case):
    """A target touching the frame's edges (the crop clipped to the frame); an all-black frame (no corner); a frame of
    values 0-3, whose strongest response the noise could reach (the whole frame searched), and one of noise up to
    39 DN: the same corners."""
    rng = np.random.default_rng(7)
    img = {
        "edge": lambda: frame(rng, box=(0, 200, 500, 640)),
        "black": lambda: np.zeros((480, 640), np.uint8),
        "faint": lambda: rng.integers(0, 4, (480, 640)).astype(np.uint8),
        "noisy": lambda: rng.integers(0, 40, (480, 640)).astype(np.uint8),
    }[case]()
    for mask in (None, border_mask(img.shape)):
        assert np.array_equal(klt.keypoints(img, "gftt", mask)[0], whole(img, mask))


@pytest.mark.parametrize("level", [1, 2, 5])
def test_noise_response_bounds_the_response_of_any_window_of_small_values(level):
    """Checkerboards, stripes and random images with values in ``[0, level]``: OpenCV's response never above the
    bound, which is not loose by more than a factor 4."""
    rng = np.random.default_rng(level)
    i, j = np.indices((40, 40))
    images = [(i + j) % 2, i % 2, j % 2, (i // 2 + j // 2) % 2, (i % 3 == 0) & (j % 2 == 0)]
    images += [rng.integers(0, 2, (40, 40)) for _ in range(50)]
    worst = max(float(cv2.cornerMinEigenVal((level * np.asarray(a)).astype(np.uint8), 7, 3).max()) for a in images)
    assert 0 < worst <= klt.noise_response(level) < 4 * worst


def test_a_frame_whose_noise_could_reach_the_threshold_is_searched_whole(monkeypatch):
    """A black frame with a patch of values 0-3: the crop's strongest response is within the noise bound's reach, so
    the whole frame is searched (not the crop around the patch)."""
    rng = np.random.default_rng(2)
    img = np.zeros((480, 640), np.uint8)
    img[200:260, 300:380] = rng.integers(0, 4, (60, 80))
    seen = spied(monkeypatch)
    pts = klt.keypoints(img, "gftt")[0]
    monkeypatch.undo()
    assert seen == [img.shape] and np.array_equal(pts, whole(img, None))
