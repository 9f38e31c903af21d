"""Which features the stereo rig sees at each step (docs/realism.md).

The thesis's rule (``core.camera.visible``: in front of the cameras, ``y > 0``) is the
default. Options narrow it:

- a pixel camera (``camera.resolution_px``): the feature projects inside both images;
- ``measurements.occlusion`` (with ``target.shape``): its surface faces both cameras
  and no part of the body lies between it and either camera (ray tests of
  core/shapes.py, in the target frame, with the cameras at ``D^T (c - rho_0)``);
- ``measurements.illumination``: its surface faces the Sun and the body does not
  shadow it (a ray toward the Sun, direction fixed in ``L``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..config.resolve import Setup
from ..core import camera, geometry, shapes, state as st
from ..core import quaternion as qt

Array = NDArray[np.float64]


def visible(setup: Setup, x: Array) -> Array:
    """Visibility ``(..., N)`` of the features of the states ``x (..., n)``."""
    vis = camera.visible(x)
    sensor = setup.sensor
    cam = sensor.pixels
    if cam is not None:
        rho_i, _ = camera.feature_kinematics(x)
        vis = vis & geometry.in_image(rho_i, setup.baseline, cam.bounds())
    if sensor.shape is not None and (sensor.occlusion or sensor.sun is not None):
        vis = vis & body_visibility(setup, x)
    return vis


def body_visibility(setup: Setup, x: Array) -> Array:
    """``(..., N)``: seen by both cameras past the body (occlusion) and lit (illumination), as enabled."""
    sensor = setup.sensor
    shape = sensor.shape
    D = qt.dcm(qt.normalize(x[..., st.QUAT]))
    P = st.points(x)  # (..., N, 3) in T
    n = np.broadcast_to(sensor.normals, P.shape)
    ok = np.ones(P.shape[:-1], bool)

    def to_body(v):  # L-frame vectors (..., 3) -> T components, broadcast over the features
        return np.einsum("...ji,...j->...i", D, v)[..., None, :]

    # each test only where the tests before it passed (shapes.sees' ``where``: the same booleans, fewer ray tests)
    if sensor.occlusion:
        rho = x[..., st.RHO]
        for c in (np.zeros(3), np.array([setup.baseline, 0.0, 0.0])):
            ok = shapes.sees(shape, P, n, to_body(c - rho), where=ok)
    if sensor.sun is not None:
        s = to_body(np.broadcast_to(sensor.sun, x.shape[:-1] + (3,)))
        ok = shapes.sees(shape, P, n, P + shape.extent * s, where=ok)
    return ok
