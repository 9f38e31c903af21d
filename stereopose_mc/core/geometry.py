"""Sensor geometry: which points a stereo rig sees (field of view, rays against a body).

Pure numerics, batched (leading axes ``...``), SI. The rig is that of ``core.camera``:
right camera at the origin of ``L``, left camera at ``[b, 0, 0]``, both looking along
``+y``; normalized image coordinates ``u = (x - c_x) / y``, ``v = z / y``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def in_image(rho_i: Array, baseline: float, bounds: tuple[float, float, float, float]) -> Array:
    """``(...)`` bool: the points ``rho_i (..., 3)`` are in front of and inside both images.

    ``bounds = (u_min, u_max, v_min, v_max)`` in normalized coordinates (the same for
    both cameras), edges included.
    """
    x, y, z = np.moveaxis(rho_i, -1, 0)
    u0, u1, v0, v1 = bounds
    with np.errstate(divide="ignore", invalid="ignore"):
        u_r, u_l, v = x / y, (x - baseline) / y, z / y
    front = y > 0.0
    return front & (u_r >= u0) & (u_r <= u1) & (u_l >= u0) & (u_l <= u1) & (v >= v0) & (v <= v1)
