"""Which features the stereo rig sees at each step (docs/realism.md).

The thesis's rule (``core.camera.visible``: in front of the cameras, ``y > 0``) is the
default. With a pixel camera (``camera.resolution_px``) a feature must also project
inside both images.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..config.resolve import Setup
from ..core import camera, geometry

Array = NDArray[np.float64]


def visible(setup: Setup, x: Array) -> Array:
    """Visibility ``(..., N)`` of the features of the states ``x (..., n)``."""
    vis = camera.visible(x)
    cam = setup.sensor.pixels
    if cam is not None:
        rho_i, _ = camera.feature_kinematics(x)
        vis = vis & geometry.in_image(rho_i, setup.baseline, cam.bounds())
    return vis
