"""The tracker's affine Lucas-Kanade refinement (sim/tracker/affine.py): its sampling, its warp, its match."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays
from scipy.ndimage import gaussian_filter, map_coordinates

from stereopose_mc.sim.tracker import affine

finite = st.floats(-1e3, 1e3, allow_nan=False)


@settings(max_examples=50, deadline=None)
@given(A=arrays(np.float64, (3, 2, 2), elements=finite), t=arrays(np.float64, (3, 2), elements=finite),
       X=arrays(np.float64, (5, 2), elements=finite))  # fmt: skip
def test_warped_offsets_are_the_einsum_of_the_warp(A, t, X):
    """``W(x) = A x + t``, the same numbers as the einsum it replaces (two products, summed in the same order)."""
    ref = np.einsum("nij,mj->nmi", A, X) + t[:, None, :]
    assert np.array_equal(affine.warped(A, t, X), ref)


def test_warped_offsets_by_hand():
    A = np.array([[[2.0, 0.0], [0.0, 3.0]], [[0.0, -1.0], [1.0, 0.0]]])  # a scaling; a quarter turn
    t = np.array([[10.0, 20.0], [0.0, 0.0]])
    X = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    w = affine.warped(A, t, X)
    assert w.shape == (2, 3, 2)
    assert w[0].tolist() == [[12.0, 20.0], [10.0, 23.0], [12.0, 23.0]]
    assert w[1].tolist() == [[0.0, 1.0], [-1.0, 0.0], [-1.0, 1.0]]


def test_sample_is_bilinear_with_nearest_edges_by_hand():
    """On the ramp ``I[row, col] = 10 row + col`` a bilinear sample at OpenCV ``(x, y)`` is ``10 y + x``; outside the
    image the nearest edge pixel's value (``mode="nearest"``)."""
    img = (10 * np.arange(6)[:, None] + np.arange(8)[None, :]).astype(np.uint8)
    pts = np.array([[1.5, 2.25], [0.0, 0.0], [6.75, 4.5], [-3.0, 2.0], [7.0, 9.0]])
    assert affine.sample(img, pts).tolist() == [24.0, 0.0, 51.75, 20.0, 57.0]


def test_sample_of_an_8_bit_image_is_that_of_its_float32_copy():
    """An 8-bit frame is read as it is (no float32 copy of the whole image per call): the same numbers as the
    interpolation of the float32 copy, rounded to float32, at points inside, on and beyond the edges."""
    rng = np.random.default_rng(5)
    img = rng.integers(0, 256, (64, 80), dtype=np.uint8)
    pts = rng.uniform(-4.0, 84.0, (500, 2))
    p = pts.reshape(-1, 2)
    ref = map_coordinates(img.astype(np.float32), [p[:, 1], p[:, 0]], order=1, mode="nearest").astype(float)
    got = affine.sample(img, pts)
    assert got.dtype == np.float64 and np.array_equal(got, ref)
    f64 = img.astype(np.float64) + 0.1  # not representable in float32: read through a float32 copy, as before
    ref64 = map_coordinates(f64.astype(np.float32), [p[:, 1], p[:, 0]], order=1, mode="nearest").astype(float)
    assert np.array_equal(affine.sample(f64, pts), ref64)


def test_refine_recovers_a_known_affine_warp():
    """A window of a smooth texture found in an image warped by a known affine ``W(x) = A x + t`` (and a brightness
    gain and offset): from the identity one pixel off and without the deformation penalty, the refinement returns
    ``A`` to 5e-3 and ``t`` to 0.02 px, with an NCC near 1; with it (the tracker's ``PRIOR``), a deformation between
    the start and the truth, on every entry."""
    rng = np.random.default_rng(11)
    tex = gaussian_filter(rng.normal(size=(160, 160)), 2.0)
    tex = 40.0 + 160.0 * (tex - tex.min()) / np.ptp(tex)
    w = 15
    c = np.array([[80.0, 80.0], [70.0, 90.0]])  # template centres (x, y) in the texture
    T, SD = affine.templates(tex, c, w)
    A_true = np.array([[1.03, 0.02], [-0.015, 0.97]])
    t_true = np.array([[83.4, 78.8], [71.9, 92.3]])  # where each centre is seen in the image
    # the image: I(A (u - c) + t) = 0.9 tex(u) + 5 near each centre; by the inverse warp u = c + A^-1 (y - t), as
    # one image per window (the two warps differ by their translations only)
    Ai = np.linalg.inv(A_true)
    found = []
    for k in range(2):
        yy, xx = np.mgrid[0:160, 0:160].astype(float)
        y = np.stack([xx.ravel(), yy.ravel()], -1) - t_true[k]
        u = c[k] + y @ Ai.T
        img = 0.9 * map_coordinates(tex, [u[:, 1], u[:, 0]], order=3, mode="nearest").reshape(160, 160) + 5.0
        start = (T[k:k + 1], SD[k:k + 1], np.eye(2)[None], t_true[k:k + 1] + [1.0, -0.8], w)
        A, t, q = affine.refine(img, *start, prior=0.0)
        Ap, _, _ = affine.refine(img, *start)
        found.append((A[0], t[0], q[0], Ap[0]))
    assert all(f[2] > 0.999 for f in found)
    assert np.allclose([f[0] for f in found], A_true, atol=5e-3)  # a sixth of the deformation (0.03)
    assert np.allclose([f[1] for f in found], t_true, atol=0.02)  # px (bilinear samples of a 15 x 15 window)
    for f in found:  # the penalty pulls toward the start (the identity), not past it nor past the truth
        d, d_true = f[3] - np.eye(2), A_true - np.eye(2)
        assert np.all(d * d_true > 0) and np.all(np.abs(d) < np.abs(d_true))
