"""Sensor geometry (core/geometry.py) on hand-built cases."""

from __future__ import annotations

import numpy as np

from stereopose_mc.core import geometry

BOUNDS = (-0.5, 0.5, -0.25, 0.25)  # u in [-0.5, 0.5], v in [-0.25, 0.25]


def test_in_image_by_hand():
    b = 1.0
    pts = np.array([
        [0.5, 10.0, 0.0],    # u_R = 0.05, u_L = -0.05: inside
        [5.0, 10.0, 0.0],    # u_R = 0.5 (edge), u_L = 0.4: inside
        [5.5, 10.0, 0.0],    # u_R = 0.55: outside the right image
        [-4.5, 10.0, 0.0],   # u_R = -0.45, u_L = -0.55: outside the left image only
        [0.5, 10.0, 2.6],    # v = 0.26: outside
        [0.5, -10.0, 0.0],   # behind
        [0.0, 0.0, 0.0],     # at the camera
    ])  # fmt: skip
    np.testing.assert_array_equal(geometry.in_image(pts, b, BOUNDS), [True, True, False, False, False, False, False])


def test_in_image_is_batched():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(4, 5, 3)) + [0, 5, 0]
    flat = geometry.in_image(pts.reshape(-1, 3), 0.3, BOUNDS).reshape(4, 5)
    np.testing.assert_array_equal(geometry.in_image(pts, 0.3, BOUNDS), flat)
